"""Training: a 3-iteration mmengine run, weights-only checkpoints, and an exact resume."""

from __future__ import annotations

import copy
import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from omnilidar.generator.text import build_prompt_cache
from omnilidar.checkpoints import from_plain, to_plain
from omnilidar.generator.checkpoint import load_generator
from omnilidar.generator.training import train_generator
from test_generator_fixtures import make_domains, one_torch_thread, tiny_settings  # noqa: F401


class FakeEncoder:
    """Deterministic stand-in for the text model (the real one is tested in test_generator_text)."""

    kind, model_name, dim = "fake", "fake", 12

    def encode(self, prompts):
        g = torch.Generator().manual_seed(0)
        tok = torch.randn(len(prompts), 5, self.dim, generator=g)
        mask = torch.ones(len(prompts), 5, dtype=torch.bool)
        mask[:, 3:] = torch.tensor([len(p) % 2 == 0 for p in prompts])[:, None]
        return tok, mask


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("train")
    settings = tiny_settings()
    index = make_domains(root, settings)
    prompts = root / "prompts.pt"
    torch.save(build_prompt_cache(settings["prompts"], FakeEncoder()), prompts)
    summary = train_generator(settings, index, prompts, root / "work", root / "ckpt.pt", seed=3)
    return root, settings, index, prompts, summary


def test_three_iterations_write_weights_only_checkpoints(trained):
    root, settings, _, _, summary = trained
    assert summary["iterations"] == 3
    run_dir = root / "work"
    assert summary["work_dir"] == str(run_dir) and summary["resumed_from"] == 0
    ckpts = sorted(run_dir.glob("iter_*.pth"))
    assert [c.name for c in ckpts] == ["iter_2.pth", "iter_3.pth"]
    assert (run_dir / "last_checkpoint").read_text() == "iter_3.pth"  # relative: a copied tree reads its own
    for c in ckpts:  # torch >= 2.6 default: weights_only=True must work on our own checkpoints
        ck = torch.load(c, map_location="cpu", weights_only=True)
        assert ck["meta"]["omnilidar"]["config"] == settings
        stored = ck["meta"]["omnilidar"]["provenance"]
        assert stored["command"] == "train-generator" and stored["seed"] == 3 and len(stored["code"]) == 16
        assert set(stored["inputs"]) == {"domains", "prompts"} and "torch" in stored["versions"]
        assert "ema_state_dict" in ck and "optimizer" in ck
        hub = ck["message_hub"]["log_scalars"]
        assert hub and all(isinstance(v, dict) for v in hub.values())
    final = torch.load(root / "ckpt.pt", map_location="cpu", weights_only=True)
    assert final["config"] == settings and final["domains"] == ["Vehicle", "Fog", "Beam32"]
    assert all(torch.isfinite(v).all() for v in final["state_dict"].values() if v.is_floating_point())


def test_final_checkpoint_loads_into_a_fresh_denoiser(trained):
    root = trained[0]
    denoiser, payload = load_generator(root / "ckpt.pt")
    assert payload["iterations"] == 3
    x = torch.zeros(1, 2, 16, 64)
    tok = torch.zeros(1, 5, 12)
    out = denoiser(x, torch.zeros(1), torch.zeros(1, dtype=torch.long), tok, torch.ones(1, 5, dtype=torch.bool))
    assert out.shape == x.shape and torch.isfinite(out).all()


def test_resume_after_interruption_reproduces_the_uninterrupted_run(trained):
    root, settings, index, prompts, summary = trained
    run_dir = root / "work"
    # Simulate a crash right after the iteration-2 checkpoint: a second work dir holding it only,
    # its marker an absolute path into the first tree (as mmengine writes it): it must read its own.
    run2 = root / "work2"
    run2.mkdir(parents=True)
    (run2 / "iter_2.pth").write_bytes((run_dir / "iter_2.pth").read_bytes())
    (run2 / "last_checkpoint").write_text(str(run_dir / "iter_2.pth"))
    resumed = train_generator(settings, index, prompts, run2, root / "ckpt2.pt", seed=3)
    assert resumed["resumed_from"] == 2
    assert resumed["iterations"] == 3
    # The cost carried over: the resumed run's total includes what iteration 2's checkpoint recorded.
    before = torch.load(run2 / "iter_2.pth", weights_only=True)["meta"]["omnilidar"]["cost"]["train_cpu_seconds"]
    assert before > 0 and resumed["train_cpu_seconds"] > before
    a = torch.load(root / "ckpt.pt", weights_only=True)["state_dict"]
    b = torch.load(root / "ckpt2.pt", weights_only=True)["state_dict"]
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=1e-6, msg=k)
    logs = "\n".join(p.read_text() for p in run2.rglob("*.log"))
    assert "resumed epoch: 0, iter: 2" in logs


def test_message_hub_round_trip_is_weights_only_safe(tmp_path):
    from mmengine.logging import HistoryBuffer

    buf = HistoryBuffer([1.0, 2.0], [1, 1], max_length=7)
    hub = {"log_scalars": {"loss": buf}, "runtime_info": {"a": np.float64(2.5), "arr": np.arange(3)}, "x": [np.int64(4)]}
    plain = to_plain(hub)
    path = tmp_path / "hub.pt"
    torch.save(plain, path)
    back = from_plain(torch.load(path, weights_only=True))
    assert isinstance(back["log_scalars"]["loss"], HistoryBuffer)
    assert back["log_scalars"]["loss"].mean() == pytest.approx(1.5)
    assert back["log_scalars"]["loss"].max_length == 7
    assert back["runtime_info"]["a"] == 2.5 and back["x"] == [4]
    np.testing.assert_array_equal(back["runtime_info"]["arr"], np.arange(3))
    # The unconverted hub is exactly what weights_only refuses.
    torch.save(hub, tmp_path / "raw.pt")
    with pytest.raises(pickle.UnpicklingError):
        torch.load(tmp_path / "raw.pt", weights_only=True)


def test_trajectory_settings_leave_out_only_what_extends_a_run(trained):
    from omnilidar.generator.training import trajectory_settings

    settings = trained[1]
    other = json.loads(json.dumps(settings))
    other["training"]["lr"] *= 2
    longer = json.loads(json.dumps(settings))
    longer["training"]["iterations"] = 10
    longer["sampling"]["steps"] = 99
    assert trajectory_settings(other) != trajectory_settings(settings)
    assert trajectory_settings(longer) == trajectory_settings(settings)  # extending a run resumes it


def _ema_gap(root, summary) -> float:
    """Distance between the final EMA weights and the raw weights of the last step."""
    final = torch.load(root / summary["out"], map_location="cpu", weights_only=True)["state_dict"]
    last = torch.load(sorted(Path(summary["work_dir"]).glob("iter_*.pth"))[-1],
                      map_location="cpu", weights_only=True)["ema_state_dict"]  # mmengine swaps: raw here
    raw = {k[len("module.denoiser."):]: v for k, v in last.items() if k.startswith("module.denoiser.")}
    return float(sum((final[k].float() - raw[k].float()).square().sum() for k in raw if final[k].is_floating_point()))


def test_ema_warmup_keeps_short_runs_off_the_initial_weights(trained):
    """Without warm-up (decay 0.9, 3 steps) the EMA keeps 0.9^3 = 73 % of the initial weights;
    with gamma = 1 it starts as a copy and anneals, ending much closer to the trained weights."""
    from omnilidar.generator.training import ema_hook

    root, settings, index, prompts, summary = trained
    assert type(ema_hook({"ema_decay": 0.9, "ema_warmup": 0})).__name__ == "EMAHook"
    assert ema_hook({"ema_decay": 0.9, "ema_warmup": 5}).ema_cfg["type"] == "MomentumAnnealingEMA"
    warm = dict(settings, training=dict(settings["training"], ema_warmup=1))
    warm_summary = train_generator(warm, index, prompts, root / "work_warm", root / "ckpt_warm.pt", seed=3)
    gap_plain = _ema_gap(root, dict(summary, out="ckpt.pt"))
    gap_warm = _ema_gap(root, dict(warm_summary, out="ckpt_warm.pt"))
    assert gap_plain > 0 and gap_warm < 0.5 * gap_plain


def test_changed_input_contents_start_fresh_and_say_so(trained, capsys):
    """Same work dir, same settings and seed, other domain data: the finished checkpoint
    is not this job's; the run starts fresh and writes other weights."""
    root, settings, _, prompts, _ = trained
    work = root / "work_inputs"
    first = make_domains(root / "data_a", settings, seed=0)
    train_generator(settings, first, prompts, work, root / "inputs_a.pt", seed=3)
    other = make_domains(root / "data_b", settings, seed=1)  # same layout, other pixels
    capsys.readouterr()
    again = train_generator(settings, other, prompts, work, root / "inputs_b.pt", seed=3)
    log = capsys.readouterr().out
    assert again["resumed_from"] == 0
    assert "starting fresh" in log and "input contents changed: domains" in log
    a = torch.load(root / "inputs_a.pt", weights_only=True)["state_dict"]
    b = torch.load(root / "inputs_b.pt", weights_only=True)["state_dict"]
    assert any(not torch.equal(a[k], b[k]) for k in a)


def test_raising_iterations_resumes_from_a_moved_work_dir(trained, capsys):
    """A finished run copied elsewhere (the original removed, so nothing outside the copy
    can be read) resumes at its last iteration when ``iterations`` is raised."""
    root, settings, index, prompts, summary = trained
    moved = root / "moved" / "work"
    shutil.copytree(root / "work", moved)
    hidden = root / "work_hidden"
    (root / "work").rename(hidden)
    try:
        longer = json.loads(json.dumps(settings))
        longer["training"]["iterations"] = 4
        capsys.readouterr()
        resumed = train_generator(longer, index, prompts, moved, root / "ckpt_longer.pt", seed=3)
        log = capsys.readouterr().out
    finally:
        hidden.rename(root / "work")
    assert resumed["resumed_from"] == 3 and resumed["iterations"] == 4
    assert f"resuming at iteration 3 from iter_3.pth in {moved}" in log
    assert str(hidden) not in log and str(root / "work") + "/" not in log
    assert sorted(p.name for p in moved.glob("iter_*.pth"))[-1] == "iter_4.pth"


def test_training_on_azimuth_windows_gives_a_full_sweep_generator(tmp_path):
    """crop_width trains on windows, and the checkpoint still denoises the whole image."""
    from omnilidar.generator.diffusion import generate

    settings = tiny_settings(crop_width=16)
    index = make_domains(tmp_path, settings)
    prompts = tmp_path / "prompts.pt"
    torch.save(build_prompt_cache(settings["prompts"], FakeEncoder()), prompts)
    full = train_generator(tiny_settings(), index, prompts, tmp_path / "w_full", tmp_path / "full.pt", seed=3)
    windowed = train_generator(settings, index, prompts, tmp_path / "w_crop", tmp_path / "crop.pt", seed=3)
    assert windowed["weights_digest"] != full["weights_digest"]  # the windows changed what it learned
    denoiser, _ = load_generator(tmp_path / "crop.pt")
    vehicle = torch.load(prompts, weights_only=True)["domains"]["Vehicle"]
    images = generate(denoiser, 0, vehicle["tokens"][0], vehicle["mask"][0], [0, 1], (16, 64), steps=2)
    assert images.shape == (2, 2, 16, 64) and torch.isfinite(images).all()


def test_loss_weighting_reaches_the_trainer(trained, tmp_path):
    """diffusion.loss_weighting v_uniform trains other weights than min-SNR from the same seed, and
    the checkpoint records it (so a changed weighting is a changed generator)."""
    root, settings, index, prompts, summary = trained
    v = copy.deepcopy(settings)
    v["diffusion"]["loss_weighting"] = "v_uniform"
    other = train_generator(v, index, prompts, tmp_path / "work", tmp_path / "v.pt", seed=3)
    assert other["weights_digest"] != summary["weights_digest"]
    assert torch.load(tmp_path / "v.pt", weights_only=True)["config"]["diffusion"]["loss_weighting"] == "v_uniform"
    assert settings["diffusion"]["loss_weighting"] == "min_snr"  # the default


def test_domain_mean_prior_is_computed_from_the_domains_and_saved(trained, tmp_path):
    """diffusion.prior domain_mean: the checkpoint carries each domain's mean training image, the
    loaded generator has it, and it trains other weights than the default from the same seed, afresh
    in a work dir the default finished."""
    from omnilidar.generator.data import RangeImageDataset, load_range_image, read_domains_index

    root, settings, index, prompts, summary = trained
    p = copy.deepcopy(settings)
    p["diffusion"]["prior"] = "domain_mean"
    shutil.copytree(root / "work", tmp_path / "work")  # the default's finished run: not this job's to resume
    other = train_generator(p, index, prompts, tmp_path / "work", tmp_path / "p.pt", seed=3)
    assert other["resumed_from"] == 0 and other["weights_digest"] != summary["weights_digest"]
    domains = read_domains_index(index)
    shape = (settings["range_image"]["height"], settings["range_image"]["width"])
    first = next(iter(domains))
    expected = np.mean([load_range_image(f, shape) for f in domains[first]["files"]], axis=0)
    denoiser, payload = load_generator(tmp_path / "p.pt")
    assert payload["config"]["diffusion"]["prior"] == "domain_mean"
    assert np.allclose(denoiser.prior_mean[0].numpy(), expected, atol=1e-6)
    spans = {n: (0, 1) for n in domains}
    capped = RangeImageDataset(domains, shape, spans).domain_means(max_scans=2)
    assert capped.shape == denoiser.prior_mean.shape and not torch.equal(capped, denoiser.prior_mean.cpu())


@pytest.mark.parametrize("until", [0, 3, 7])
def test_a_segment_must_end_inside_the_training(trained, tmp_path, until):
    from omnilidar.errors import InputError

    root, settings, index, prompts, _ = trained  # 3 iterations
    with pytest.raises(InputError, match=f"--until {until} must lie between 0 and the 3 iterations"):
        train_generator(settings, index, prompts, tmp_path / "work", tmp_path / "seg.json", seed=3, until=until)
    assert not (tmp_path / "seg.json").exists() and not (tmp_path / "work").exists()


@pytest.mark.parametrize("bf16", [True, False])
def test_cpu_training_autocasts_bf16_only_where_the_cpu_multiplies_it_natively(trained, tmp_path, monkeypatch, bf16):
    """training.bf16 on a CPU: the denoiser's convolutions run in bf16 where the CPU has native bf16
    (faked here both ways), in fp32 otherwise; the summary says which."""
    from omnilidar.generator import training

    _, settings, index, prompts, _ = trained
    settings = json.loads(json.dumps(settings))
    settings["training"].update(bf16=True, iterations=1)
    monkeypatch.setattr(training, "cpu_has_native_bf16", lambda: bf16)
    seen = set()
    original = torch.nn.Conv2d.forward
    monkeypatch.setattr(torch.nn.Conv2d, "forward", lambda self, x: seen.add((out := original(self, x)).dtype) or out)
    summary = train_generator(settings, index, prompts, tmp_path / "work", tmp_path / "ckpt.pt", seed=3)
    assert summary["precision"] == ("bf16 autocast" if bf16 else "fp32")
    assert seen == ({torch.bfloat16} if bf16 else {torch.float32})
    final = torch.load(tmp_path / "ckpt.pt", map_location="cpu", weights_only=True)
    assert all(v.dtype != torch.bfloat16 for v in final["state_dict"].values())
