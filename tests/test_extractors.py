"""Generation-metric extractors: protocol preprocessing and aggregation, weight loading, self-training."""

from __future__ import annotations

import io
import pickle
import random
import tarfile
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from omnilidar.data.range_image import RangeImageSpec, encode, project
from omnilidar.errors import InputError
from omnilidar.io.semantickitti import write_label, write_points
from omnilidar.metrics.extractors.pointnet import PointNet
from omnilidar.metrics.extractors.rangenet import RangeNet, band_average, frd_indices, protocol_image
from omnilidar.metrics.extractors.sparse_features import BIN_EDGES, distance_bin_means
from omnilidar.metrics.extractors.views import range_views
from omnilidar.metrics.extractors.weights import (
    LoadedExtractor,
    build_model,
    load_extractor,
    parse_pairs,
    save_self_trained,
    wrap,
)
from omnilidar.metrics.generation import compare, domain_statistics, set_features

SPEC = RangeImageSpec(32, 256, 3.0, -25.0, 1.45, 80.0)


@pytest.fixture(scope="module")
def real_images(synthetic_sweeps) -> np.ndarray:
    """Range images of two full HDL-64E sweeps (synthetic: the "real" set of the metrics)."""
    out = []
    for scan in synthetic_sweeps:
        proj = project(scan.points, SPEC)
        out.append(encode(proj.range_img, proj.intensity_img, SPEC))
    return np.stack(out)


def tiny(kind: str) -> LoadedExtractor:
    arch = {"frd": {"in_channels": 5, "depth": 53, "width": 4}, "frid": {"in_channels": 4, "depth": 21, "width": 4},
            "fsvd": {"width": "W16"}, "fpvd": {"width": "W16"}, "fpd": {"num_classes": 16}}[kind]
    model = build_model(kind, arch, generator=torch.Generator().manual_seed(0))
    return LoadedExtractor(kind, wrap(kind, model), "self-trained:test", False, arch)


# --------------------------------------------------------------------------- protocol pieces


def test_views_mask_to_protocol_band(real_images):
    v = range_views(real_images, SPEC)
    assert v["xyz"].shape == (2, 3, 32, 256)
    inside = (v["depth"] > 0.5) & (v["depth"] < 63.0)
    assert np.array_equal(v["mask"], inside)
    assert np.all(v["xyz_masked"][:, :, ~v["mask"][0]][0] == 0)
    # points are the masked pixels, their norms equal the decoded ranges
    norms = np.linalg.norm(v["points"][0], axis=1)
    np.testing.assert_allclose(np.sort(norms), np.sort(v["depth"][0][v["mask"][0]]), rtol=1e-5)
    img = protocol_image(v["depth"], v["xyz"], v["reflectance"], True)
    assert img.shape == (2, 5, 32, 256) and np.all(img[:, :, ~v["mask"][0]][0] == 0)


def test_frd_indices_follow_python_random_seed_0():
    state = random.getstate()
    try:
        random.seed(0)
        expected = random.sample(range(32 * 64 * 1024), 4096)
    finally:
        random.setstate(state)
    idx = frd_indices(32 * 64 * 1024)
    assert idx.tolist() == expected and len(set(idx.tolist())) == 4096
    with pytest.raises(InputError):
        frd_indices(100)


def test_band_average_is_16_bands_channel_major():
    fmap = torch.arange(2 * 3 * 32 * 4, dtype=torch.float64).reshape(2, 3, 32, 4)
    out = band_average(fmap)
    assert out.shape == (2, 48)
    # channel 1, band 5 = mean of rows 10, 11 of channel 1
    assert out[0, 16 + 5] == fmap[0, 1, 10:12].mean()


def test_distance_bins_edges_and_empty_bins():
    assert BIN_EDGES[0] == 0 and BIN_EDGES[1] == 7.25 and BIN_EDGES[-1] == 56 and len(BIN_EDGES) == 17
    # a symmetric pair per distance keeps the centroid at the origin (voxel units of 0.05 m)
    d_m = np.array([1.0, 8.0, 60.0])
    pos = np.concatenate([np.stack([d_m / 0.05, 0 * d_m, 0 * d_m], 1), np.stack([-d_m / 0.05, 0 * d_m, 0 * d_m], 1)])
    feats = torch.tensor([[1.0], [2.0], [5.0], [3.0], [4.0], [7.0]])
    out = distance_bin_means(feats, torch.from_numpy(pos), torch.zeros(6, dtype=torch.long), 1).numpy()[0]
    assert out.shape == (16,)
    assert out[0] == 2.0  # (1 + 3) / 2 at 1 m
    assert out[1] == 3.0  # (2 + 4) / 2 at 8 m (bin 7.25-10.5)
    assert np.count_nonzero(out) == 2  # 60 m is beyond the last edge; empty bins are 0


# --------------------------------------------------------------------------- features and metrics


def test_identical_sets_score_zero_and_shift_scores_positive(real_images):
    ex = {k: tiny(k) for k in ("frd", "frid", "fpd")}
    a = set_features(np.concatenate([real_images, real_images[::-1]]), SPEC, ex)
    same = compare(a, a, ex)
    for m in ("JSD", "MMD", "FRD", "FRID", "FPD"):
        assert same[m] == 0.0
    shifted = real_images.copy()
    shifted[:, 0] = np.roll(shifted[:, 0], 64, axis=2)  # rotate every scan by 90 degrees
    b = set_features(np.concatenate([shifted, shifted[::-1]]), SPEC, ex)
    diff = compare(a, b, ex)
    assert diff["JSD"] > 0.05 and diff["FRD"] > 0 and diff["FPD"] > 0
    assert diff["weights"]["FRD"] == "self-trained:test" and diff["comparable_with_paper"]["FRD"] is False
    assert a.features["fpd"].shape == (4, 1808) and a.features["frd"].shape == (4, 4096)


def test_sparse_features_shape_and_empty_scan(real_images):
    ex = {"fsvd": tiny("fsvd")}
    empty = -np.ones_like(real_images[:1])
    fs = set_features(np.concatenate([real_images[:1], empty]), SPEC, ex)
    assert fs.features["fsvd"].shape == (2, 16 * 48)
    assert np.isfinite(fs.features["fsvd"]).all() and not fs.features["fsvd"][1].any()


def test_all_empty_generated_set_gives_no_nan(real_images):
    empty = -np.ones((3, 2, 32, 256), np.float32)
    ex = {"frid": tiny("frid")}
    out = compare(set_features(real_images, SPEC, ex), set_features(empty, SPEC, ex), ex)
    assert out["JSD"] is None and out["notes"]
    assert np.isfinite(out["FRID"])


def test_domain_statistics_see_beam_reduction(real_images):
    full = domain_statistics(real_images, SPEC)
    half = real_images.copy()
    half[:, :, 1::2] = -1.0  # every other row empty
    red = domain_statistics(half, SPEC)
    assert red["empty_row_fraction"] >= 0.5 > full["empty_row_fraction"]
    assert red["points_per_scan"] < 0.6 * full["points_per_scan"]
    assert 0 <= full["near_range_fraction"] < 1 and len(full["elevation_profile"]) == 32


# --------------------------------------------------------------------------- weights


def _bonnetal_archive(tmp_path: Path, model: RangeNet) -> Path:
    state = model.state_dict()
    parts = {"backbone": "backbone.", "segmentation_decoder": "decoder.", "segmentation_head": "head."}
    path = tmp_path / "darknet_tiny.tar.gz"
    with tarfile.open(path, "w:gz") as tar:
        for name, prefix in parts.items():
            buf = io.BytesIO()
            torch.save({k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}, buf)
            info = tarfile.TarInfo(f"darknet_tiny/{name}")
            info.size = buf.tell()
            buf.seek(0)
            tar.addfile(info, buf)
        cfg = yaml.safe_dump({"dataset": {"sensor": {"img_means": [1, 2, 3, 4, 5], "img_stds": [2, 2, 2, 2, 2]}}})
        info = tarfile.TarInfo("darknet_tiny/arch_cfg.yaml")
        info.size = len(cfg)
        tar.addfile(info, io.BytesIO(cfg.encode()))
    return path


def test_official_rangenet_archive_loads_in_bonnetal_layout(tmp_path, real_images):
    model = RangeNet(5, 20, 53, 4).eval()
    with torch.no_grad():  # non-trivial BN statistics so a wrong mapping would show
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.1, 0.1)
    path = _bonnetal_archive(tmp_path, model)
    loaded = load_extractor("frd", path)
    assert loaded.weights.startswith("official:") and len(loaded.weights) == len("official:") + 16
    assert loaded.comparable_with_paper is False  # width 4, not the official 32
    assert loaded.extract.mean == (1, 2, 3, 4, 5)
    ref = wrap("frd", model, (1, 2, 3, 4, 5), (2, 2, 2, 2, 2))
    views = range_views(real_images, SPEC)
    np.testing.assert_array_equal(loaded.extract(views), ref(views))


def test_official_pointnet_state_dict_is_comparable(tmp_path):
    model = PointNet(16)
    path = tmp_path / "cls_model_39.pth"
    torch.save(model.state_dict(), path)
    loaded = load_extractor("fpd", path)
    assert loaded.comparable_with_paper and loaded.arch == {"num_classes": 16}
    assert "feat.stn.fc3.weight" in model.state_dict()  # the official key names


def test_sparse_state_dict_width_is_inferred(tmp_path):
    model = build_model("fsvd", {"width": "W16"})
    path = tmp_path / "minkunet.pt"
    torch.save({"state_dict": model.state_dict()}, path)
    assert load_extractor("fsvd", path).arch["width"] == "W16"


class _Evil:
    def __reduce__(self):
        return (print, ("executed",))


def test_untrusted_pickles_and_bad_files_are_input_errors(tmp_path):
    evil = tmp_path / "evil.pth"
    evil.write_bytes(pickle.dumps({"x": _Evil()}))
    with pytest.raises(InputError, match="weights-only"):
        load_extractor("fpd", evil)
    with pytest.raises(InputError, match="not found"):
        load_extractor("fpd", tmp_path / "missing.pth")
    wrong = tmp_path / "wrong.pth"
    torch.save({"fc3.weight": torch.zeros(16, 256)}, wrong)
    with pytest.raises(InputError, match="do not fit"):
        load_extractor("fpd", wrong)
    with pytest.raises(InputError):
        parse_pairs(["frd"], "--weights")


def test_self_trained_checkpoint_round_trip_and_tag(tmp_path):
    model = build_model("frid", {"in_channels": 4, "depth": 21, "width": 4})
    path = tmp_path / "frid.pt"
    save_self_trained(path, "frid", {"in_channels": 4, "depth": 21, "width": 4}, "abc123", model, {"it": 1})
    loaded = load_extractor("frid", path)
    assert loaded.weights == "self-trained:abc123" and loaded.comparable_with_paper is False
    with pytest.raises(InputError, match="not frd"):
        load_extractor("frd", path)


# --------------------------------------------------------------------------- self-training


@pytest.fixture(scope="module")
def labelled_entries(tmp_path_factory, synthetic_sweeps) -> list[dict]:
    """Two full HDL-64E sweeps with simple labels (road below -1.5 m, building above)."""
    root = tmp_path_factory.mktemp("labelled")
    entries = []
    for name, scan in zip(("000000", "000001"), synthetic_sweeps):
        pts = scan.points
        write_points(root / f"{name}.bin", pts)
        write_label(root / f"{name}.label", np.where(pts[:, 2] < -1.5, 40, 50).astype(np.uint32))
        entries.append({"points": str(root / f"{name}.bin"), "labels": str(root / f"{name}.label")})
    return entries


@pytest.mark.parametrize("kind,arch", [
    ("frid", {"in_channels": 4, "depth": 21, "width": 4}),
    ("fsvd", {"width": "W16"}),
    ("fpd", {"num_classes": 19}),
])
def test_self_training_runs_and_tags(tmp_path, labelled_entries, kind, arch):
    from omnilidar.metrics.extractors.training import train_extractor

    schedule = {"max_scans": 2, "batch_size": 1, "iterations": 1, "lr": 1e-3, "weight_decay": 0.0}
    out = tmp_path / f"{kind}.pt"
    summary = train_extractor(kind, arch, schedule, labelled_entries, SPEC, 0, out, log=lambda *_: None)
    assert np.isfinite(summary["loss_last"]) and summary["iterations"] == 1
    loaded = load_extractor(kind, out)
    assert loaded.weights == f"self-trained:{summary['config_hash']}" and not loaded.comparable_with_paper
    if kind == "frid":  # same seed and config -> same hash and bit-identical weights (dropout included)
        out2 = tmp_path / f"{kind}_again.pt"
        again = train_extractor(kind, arch, schedule, labelled_entries, SPEC, 0, out2, log=lambda *_: None)
        assert again["config_hash"] == summary["config_hash"]
        a = torch.load(out, weights_only=True)["state_dict"]
        b = torch.load(out2, weights_only=True)["state_dict"]
        assert all(torch.equal(a[k], b[k]) for k in a)
        # The device it trains on is not part of its identity: an explicit cpu gives the same tag and weights.
        out3 = tmp_path / f"{kind}_cpu.pt"
        on_cpu = train_extractor(kind, arch, {**schedule, "device": "cpu"}, labelled_entries, SPEC, 0, out3,
                                 log=lambda *_: None)
        assert on_cpu["config_hash"] == summary["config_hash"]
        c = torch.load(out3, weights_only=True)["state_dict"]
        assert all(torch.equal(a[k], c[k]) for k in a)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without CUDA")
def test_self_training_on_cuda_without_cuda_is_one_clear_error(tmp_path, labelled_entries):
    from omnilidar.errors import InputError
    from omnilidar.metrics.extractors.training import train_extractor

    schedule = {"max_scans": 2, "batch_size": 1, "iterations": 1, "lr": 1e-3, "weight_decay": 0.0, "device": "cuda"}
    with pytest.raises(InputError, match="evaluation.extractors.training.device cuda"):
        train_extractor("fpd", {"num_classes": 19}, schedule, labelled_entries, SPEC, 0, tmp_path / "x.pt",
                        log=lambda *_: None)
    assert not (tmp_path / "x.pt").exists()


def test_across_domain_correlation_follows_domains_and_flags_flat_statistics():
    from omnilidar.metrics.generation import across_domain_correlation

    real = {"A": {"n": 1.0, "flat": 0.0}, "B": {"n": 2.0, "flat": 0.0}, "C": {"n": 4.0, "flat": 0.0}}
    same_order = {"A": {"n": 10.0, "flat": 1.0}, "B": {"n": 20.0, "flat": 2.0}, "C": {"n": 40.0, "flat": 3.0}}
    reversed_order = {"A": {"n": 4.0, "flat": 1.0}, "B": {"n": 2.0, "flat": 1.0}, "C": {"n": 1.0, "flat": 1.0}}
    r = across_domain_correlation(real, same_order, ["n", "flat"])
    assert r["n"] == pytest.approx(1.0) and r["flat"] is None  # real side does not vary
    assert across_domain_correlation(real, reversed_order, ["n"])["n"] < -0.9
    assert across_domain_correlation({"A": real["A"], "B": real["B"]}, same_order, ["n"])["n"] is None
