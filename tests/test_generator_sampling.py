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


def _sources(root, n=4):
    """``n`` distinct (2, 16, 64) training images of one domain, as build_domain writes them."""
    shard = root / "fog_shard"
    shard.mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    files = []
    for i in range(n):
        img = np.clip(rng.uniform(-0.9, 0.9, (2, 1, 1)) + 0.05 * rng.standard_normal((2, 16, 64)), -1, 1)
        files.append(shard / f"{i:06d}.npz")
        np.savez(files[-1], image=img.astype(np.float32))
    return files


def test_strength_below_one_edits_the_domains_training_scans(model_files, tmp_path):
    from omnilidar.errors import InputError
    from omnilidar.generator.sampling import source_scans, student_sampling

    root, settings, cache = model_files
    files = _sources(tmp_path)
    with pytest.raises(InputError, match="domains index"):
        _sample(root, settings, cache, tmp_path / "none", strength=0.1)
    den, payload = load_generator(root / "ckpt.pt")
    s = dict(settings["sampling"], strength=0.05)
    for out in ("a", "b"):
        sample_shard(den, payload, cache, "Fog", 0, 4, s, 5, tmp_path / out, log=lambda *_: None, sources=files)
    chosen = source_scans(files, 5, "Fog", [0, 1, 2, 3])
    assert sorted(chosen) == files  # the first len(files) scans start from different training scans
    for g, src in enumerate(chosen):
        img = np.load(tmp_path / "a" / "range" / f"{g:06d}.npz")["image"]
        np.testing.assert_array_equal(img, np.load(tmp_path / "b" / "range" / f"{g:06d}.npz")["image"])
        gaps = [np.abs(img - np.load(f)["image"]).mean() for f in files]
        assert np.argmin(gaps) == files.index(src) and gaps[files.index(src)] < 0.1  # close to its own source
    assert json.loads((tmp_path / "a" / "timing.json").read_text())["strength"] == 0.05
    # at strength 1 the sources are not used: the scans are the plain samples
    sample_shard(den, payload, cache, "Fog", 0, 2, dict(settings["sampling"], strength=1.0), 5, tmp_path / "c",
                 log=lambda *_: None, sources=files)
    _sample(root, settings, cache, tmp_path / "d", n=2)
    np.testing.assert_array_equal(np.load(tmp_path / "c/range/000000.npz")["image"],
                                  np.load(tmp_path / "d/range/000000.npz")["image"])
    # a distilled student samples its own grid from noise
    with pytest.raises(InputError, match="strength"):
        student_sampling(s, {"student": {"sampler": "ddim", "steps": 2}}, "student.pt")


def test_strength_more_noise_moves_further_from_the_source(model_files):
    root, settings, cache = model_files
    den, _ = load_generator(root / "ckpt.pt")
    e = cache["domains"]["Fog"]
    init = torch.full((2, 2, 16, 64), 0.5)
    gaps = [(generate(den, 1, e["tokens"][0], e["mask"][0], [1, 2], (16, 64), "unipc", 10, init=init,
                      strength=s) - init).abs().mean().item() for s in (0.05, 0.5, 1.0)]
    assert gaps[0] < gaps[1] < gaps[2]
    with pytest.raises(ValueError, match="init images"):
        generate(den, 1, e["tokens"][0], e["mask"][0], [1, 2], (16, 64), strength=0.5)


def test_cli_sample_edits_with_the_domains_index(model_files, tmp_path, capsys):
    root, settings, _ = model_files
    _sources(tmp_path, n=2)
    (tmp_path / "index.json").write_text(json.dumps({"domains": {"Fog": {"id": 1, "shards": ["fog_shard"]}}}))
    edit = dict(settings, sampling=dict(settings["sampling"], strength=0.3))
    args = ["sample", "--checkpoint", str(root / "ckpt.pt"), "--prompts", str(root / "prompts.pt"),
            "--settings", json.dumps(edit), "--seed", "1", "--shard", "0", "--scans-per-shard", "2"]
    assert main(args + ["--domain", "Fog", "--out", str(tmp_path / "s")]) == 2  # no index: one clear error
    assert "--domains" in capsys.readouterr().err and not (tmp_path / "s").exists()
    assert main(args + ["--domains", str(tmp_path / "index.json"), "--domain", "Vehicle",
                        "--out", str(tmp_path / "v")]) == 2
    assert "no domain 'Vehicle'" in capsys.readouterr().err
    assert main(args + ["--domains", str(tmp_path / "index.json"), "--domain", "Fog", "--out", str(tmp_path / "s")]) == 0
    assert len(list((tmp_path / "s" / "range").glob("*.npz"))) == 2
