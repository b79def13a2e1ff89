"""carry-labels: SDEdited scans labelled from their source training scans, pixel by pixel."""

from __future__ import annotations

import json

import numpy as np
import pytest

from omnilidar.cli import main
from omnilidar.data.range_image import decode, unproject
from omnilidar.errors import InputError
from omnilidar.generator.carried_labels import carry_source_labels
from omnilidar.generator.checkpoint import load_generator
from omnilidar.generator.sampling import sample_shard, source_scans
from omnilidar.generator.unet import range_image_spec
from omnilidar.io import semantickitti
from test_generator_fixtures import geometric_image, one_torch_thread  # noqa: F401
from test_generator_sampling import model_files  # noqa: F401

ROAD, BUILDING, CAR = 40, 50, 10


def _domain_shard(root, settings, n=3):
    """``n`` Fog training scans laid out as build_domain writes them (range/, velodyne/, labels/):
    road below the middle row, a car on the box the image holds, building elsewhere."""
    spec = range_image_spec(settings)
    shard = root / "fog" / "shard_0"
    for sub in ("range", "velodyne", "labels"):
        (shard / sub).mkdir(parents=True)
    rng = np.random.default_rng(3)
    files = []
    for k in range(n):
        img = geometric_image(rng, *spec.shape, kind=1)
        rng_img, inten, valid = decode(img, spec)
        label_img = np.full(spec.shape, BUILDING, np.uint16)
        label_img[spec.height // 2:] = ROAD
        box = np.abs(img[0] + 0.2) < 0.05
        box[spec.height // 2:] = False
        label_img[box] = CAR
        points = unproject(rng_img, inten, spec, mask=valid)
        semantickitti.write_points(shard / "velodyne" / f"{k:06d}.bin", points)
        semantickitti.write_label(shard / "labels" / f"{k:06d}.label", label_img[valid], np.zeros(int(valid.sum()), np.uint16))
        files.append(shard / "range" / f"{k:06d}.npz")
        np.savez(files[-1], image=img)
    return files, spec


def _nearest_labels(points, source_points, source_labels):
    d = np.linalg.norm(points[:, None, :3] - source_points[None, :, :3], axis=2)
    return source_labels[d.argmin(axis=1)]


def test_edited_scans_keep_their_sources_labels_pixel_by_pixel(model_files, tmp_path):
    root, settings, cache = model_files
    files, spec = _domain_shard(tmp_path, settings)
    den, payload = load_generator(root / "ckpt.pt")
    for strength in (0.001, 0.5):
        samples, out = tmp_path / f"s{strength}", tmp_path / f"l{strength}"
        sample_shard(den, payload, cache, "Fog", 0, 3, dict(settings["sampling"], strength=strength), 5, samples,
                     log=lambda *_: None, sources=files)
        side = carry_source_labels(samples, out, progress=False)
        assert side["strength"] == strength and len(side["scans"]) == 3
        for g, src in enumerate(source_scans(files, 5, "Fog", [0, 1, 2])):
            points = semantickitti.read_points(samples / "velodyne" / f"{g:06d}.bin")
            sem, _ = semantickitti.read_label(out / "labels" / f"{g:06d}.label", len(points))
            source_points = semantickitti.read_points(src.parent.parent / "velodyne" / f"{src.stem}.bin")
            source_sem, _ = semantickitti.read_label(src.parent.parent / "labels" / f"{src.stem}.label")
            if strength < 0.01:  # the edit is its source: every point is labelled as its nearest source point
                assert (sem == _nearest_labels(points, source_points, source_sem)).mean() > 0.97
                assert set(np.unique(sem)) == {ROAD, BUILDING, CAR}
            # at any strength a point keeps its pixel's label: road only on the lower rows,
            # and a pixel the source left empty gives no label
            rows = np.nonzero(decode(np.load(samples / "range" / f"{g:06d}.npz")["image"], spec)[2])[0]
            assert set(np.unique(sem[rows >= spec.height // 2])) <= {ROAD, 0}
            assert ROAD not in sem[rows < spec.height // 2]
        assert json.loads((samples / "sources.json").read_text())["scans"]["000000"] == str(
            source_scans(files, 5, "Fog", [0])[0])


def test_fresh_samples_and_broken_shards_are_refused_with_one_clear_error(model_files, tmp_path, capsys):
    root, settings, cache = model_files
    files, _ = _domain_shard(tmp_path, settings, n=2)
    den, payload = load_generator(root / "ckpt.pt")
    sample_shard(den, payload, cache, "Fog", 0, 2, settings["sampling"], 5, tmp_path / "fresh", log=lambda *_: None)
    assert main(["carry-labels", "--samples", str(tmp_path / "fresh"), "--out", str(tmp_path / "x")]) == 2
    assert "strength < 1" in capsys.readouterr().err and not (tmp_path / "x").exists()
    edited = tmp_path / "edited"
    sample_shard(den, payload, cache, "Fog", 0, 2, dict(settings["sampling"], strength=0.2), 5, edited,
                 log=lambda *_: None, sources=files)
    assert main(["carry-labels", "--samples", str(edited), "--out", str(tmp_path / "ok")]) == 0
    assert "2 scans labelled" in capsys.readouterr().out
    (files[0].parent.parent / "labels" / f"{files[0].stem}.label").unlink()
    with pytest.raises(InputError, match="no label file"):
        carry_source_labels(edited, tmp_path / "y", progress=False)
    assert not (tmp_path / "y").exists()


def test_keep_source_copies_one_channel_back_and_leaves_the_others_edit(model_files, tmp_path):
    root, settings, cache = model_files
    files, _ = _domain_shard(tmp_path, settings, n=2)
    den, payload = load_generator(root / "ckpt.pt")
    runs = {}
    for name, keep in (("edit", []), ("keep_i", ["intensity"]), ("keep_r", ["range"])):
        sampling = dict(settings["sampling"], strength=0.3, keep_source=keep)
        sample_shard(den, payload, cache, "Fog", 0, 2, sampling, 5, tmp_path / name, log=lambda *_: None, sources=files)
        runs[name] = [np.load(tmp_path / name / "range" / f"{g:06d}.npz")["image"] for g in range(2)]
    for g, src in enumerate(source_scans(files, 5, "Fog", [0, 1])):
        source, edit = np.load(src)["image"], runs["edit"][g]
        assert np.abs(edit - source).max() > 0.01  # the edit changes both channels
        np.testing.assert_array_equal(runs["keep_i"][g][1], source[1])
        np.testing.assert_array_equal(runs["keep_i"][g][0], edit[0])
        np.testing.assert_array_equal(runs["keep_r"][g][0], source[0])
        np.testing.assert_array_equal(runs["keep_r"][g][1], edit[1])
    assert json.loads((tmp_path / "keep_i" / "timing.json").read_text())["keep_source"] == ["intensity"]
    with pytest.raises(InputError, match="strength < 1"):
        sample_shard(den, payload, cache, "Fog", 0, 2, dict(settings["sampling"], keep_source=["range"]), 5,
                     tmp_path / "fresh", log=lambda *_: None, sources=files)


def test_range_noise_moves_only_the_returns_ranges_by_the_asked_amount_seeded(model_files, tmp_path):
    from omnilidar.generator.sampling import add_range_noise

    root, settings, cache = model_files
    files, spec = _domain_shard(tmp_path, settings, n=2)
    den, payload = load_generator(root / "ckpt.pt")
    base = dict(settings["sampling"], strength=0.001, keep_source=["intensity"])
    for name, noise in (("clean", 0.0), ("noisy", 0.02), ("noisy2", 0.02)):
        sample_shard(den, payload, cache, "Fog", 0, 2, dict(base, range_noise=noise), 5, tmp_path / name,
                     log=lambda *_: None, sources=files)
    for g in range(2):
        clean, noisy = (np.load(tmp_path / n / "range" / f"{g:06d}.npz")["image"] for n in ("clean", "noisy"))
        np.testing.assert_array_equal(noisy, np.load(tmp_path / "noisy2" / "range" / f"{g:06d}.npz")["image"])
        np.testing.assert_array_equal(noisy[1], clean[1])  # remission untouched
        returns = decode(clean, spec)[2]
        assert (noisy[0][~returns] == clean[0][~returns]).all()  # empty pixels stay empty
        moved = (noisy[0] - clean[0])[returns]
        assert abs(moved.std() - 0.02) < 0.004 and abs(moved.mean()) < 0.004
    image = np.full((2, *spec.shape), -1.0, np.float32)
    add_range_noise(image, spec, 0.5, np.random.default_rng(0))
    assert (image == -1.0).all()  # nothing to move in an empty scan
