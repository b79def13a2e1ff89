"""Sampling: determinism, shard layout, resume, atomic shard directory, CLI errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from omnilidar.cli import main
from omnilidar.generator.diffusion import generate, scan_seed
from omnilidar.generator.sampling import sample_shard
from omnilidar.generator.text import build_prompt_cache
from omnilidar.generator.checkpoint import CHECKPOINT_FORMAT, load_generator
from omnilidar.generator.unet import build_denoiser
from omnilidar.io.semantickitti import read_points
from test_generator_fixtures import one_torch_thread, tiny_settings  # noqa: F401
from test_generator_training import FakeEncoder


@pytest.fixture(scope="module")
def model_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("sample")
    settings = tiny_settings()
    cache = build_prompt_cache(settings["prompts"], FakeEncoder())
    torch.save(cache, root / "prompts.pt")
    names = ["Vehicle", "Fog", "Beam32"]
    with torch.random.fork_rng():
        torch.manual_seed(0)
        den = build_denoiser(settings, cache["dim"], len(names))
        # non-zero output layers so that the samples depend on the network
        for p in den.parameters():
            p.data.add_(0.05 * torch.randn_like(p))
    payload = {"format": CHECKPOINT_FORMAT, "state_dict": den.state_dict(), "config": settings, "domains": names,
               "text": {"encoder": "fake", "model": "fake", "dim": cache["dim"]}, "seed": 0, "iterations": 0}
    torch.save(payload, root / "ckpt.pt")
    return root, settings, cache


def _sample(root, settings, cache, out, shard=0, n=3, seed=5, domain="Fog", **sampling):
    den, payload = load_generator(root / "ckpt.pt")
    s = dict(settings["sampling"], **sampling)
    return sample_shard(den, payload, cache, domain, shard, n, s, seed, out, log=lambda *_: None)


def test_same_seed_same_scans_and_layout(model_files, tmp_path):
    root, settings, cache = model_files
    _sample(root, settings, cache, tmp_path / "a", shard=1)
    _sample(root, settings, cache, tmp_path / "b", shard=1, batch_size=3)  # other batching: float noise only
    _sample(root, settings, cache, tmp_path / "a2", shard=1)  # same settings: bit for bit
    names = sorted(p.name for p in (tmp_path / "a" / "range").iterdir())
    assert names == ["000003.npz", "000004.npz", "000005.npz"]  # global indices of shard 1
    for n in names:
        a = np.load(tmp_path / "a" / "range" / n)["image"]
        b = np.load(tmp_path / "b" / "range" / n)["image"]
        assert a.shape == (2, 16, 64) and a.dtype == np.float32
        assert np.isfinite(a).all() and a.min() >= -1 and a.max() <= 1
        np.testing.assert_array_equal(a, np.load(tmp_path / "a2" / "range" / n)["image"])
        np.testing.assert_allclose(a, b, atol=2e-3)
        pts = read_points(tmp_path / "a" / "velodyne" / n.replace(".npz", ".bin"))
        assert pts.shape[1] == 4 and np.isfinite(pts).all()
    assert not (tmp_path / "a.partial").exists()
    timing = json.loads((tmp_path / "a" / "timing.json").read_text())  # what the shard cost
    assert timing["scans"] == 3 and timing["seconds"] > 0 and timing["device"] == "cpu"
    assert timing["seconds_per_scan"] == pytest.approx(timing["seconds"] / 3)
    # another seed or another domain gives different scans
    _sample(root, settings, cache, tmp_path / "c", shard=1, seed=6)
    assert not np.allclose(np.load(tmp_path / "a/range/000003.npz")["image"], np.load(tmp_path / "c/range/000003.npz")["image"])
    assert scan_seed(5, "Fog", 3) != scan_seed(5, "Vehicle", 3) != scan_seed(5, "Fog", 4)


def test_resume_skips_written_scans_and_dir_appears_only_when_complete(model_files, tmp_path):
    root, settings, cache = model_files
    ref = tmp_path / "ref"
    _sample(root, settings, cache, ref)
    out = tmp_path / "shard"
    partial = tmp_path / "shard.partial"
    # an interrupted earlier run left one finished scan (and a stray temp file) behind
    (partial / "range").mkdir(parents=True)
    (partial / "velodyne").mkdir()
    for sub, name in (("range", "000001.npz"), ("velodyne", "000001.bin")):
        (partial / sub / name).write_bytes((ref / sub / name).read_bytes())
    stats = _sample(root, settings, cache, out)
    assert stats == {"generated": 2, "skipped": 1, "seconds": pytest.approx(stats["seconds"])}
    assert out.is_dir() and not partial.exists()
    for n in ("000000.npz", "000002.npz"):
        np.testing.assert_allclose(np.load(out / "range" / n)["image"], np.load(ref / "range" / n)["image"], atol=2e-3)
    assert _sample(root, settings, cache, out)["generated"] == 0  # complete shard: nothing to do


@pytest.mark.parametrize("sampler", ["ddpm", "ddim", "dpmpp_2m"])
def test_every_sampler_gives_finite_clamped_images(model_files, sampler):
    root, settings, cache = model_files
    den, _ = load_generator(root / "ckpt.pt")
    e = cache["domains"]["Vehicle"]
    x = generate(den, 0, e["tokens"][0], e["mask"][0], [1, 2], (16, 64), sampler=sampler, steps=4)
    assert x.shape == (2, 2, 16, 64) and torch.isfinite(x).all() and x.abs().max() <= 1


def test_cli_sample_and_unknown_domain(model_files, tmp_path, capsys):
    root, settings, _ = model_files
    args = ["sample", "--checkpoint", str(root / "ckpt.pt"), "--prompts", str(root / "prompts.pt"),
            "--settings", json.dumps(settings), "--seed", "1", "--shard", "0", "--scans-per-shard", "2"]
    assert main(args + ["--domain", "Beam32", "--out", str(tmp_path / "s")]) == 0
    assert len(list((tmp_path / "s" / "velodyne").glob("*.bin"))) == 2
    assert main(args + ["--domain", "Mars", "--out", str(tmp_path / "m")]) == 2
    assert "unknown domain 'Mars'" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()
    assert main(["sample", "--checkpoint", str(tmp_path / "nope.pt")] + args[3:] + ["--domain", "Fog", "--out", str(tmp_path / "x")]) == 2
