"""Training: a 3-iteration mmengine run, weights-only checkpoints, and an exact resume."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
import torch

from omnilidar.generator.text import build_prompt_cache
from omnilidar.checkpoints import from_plain, to_plain
from omnilidar.generator.training import load_generator, train_generator
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
    run_dir = root / "work" / summary["config_hash"]
    ckpts = sorted(run_dir.glob("iter_*.pth"))
    assert [c.name for c in ckpts] == ["iter_2.pth", "iter_3.pth"]
    for c in ckpts:  # torch >= 2.6 default: weights_only=True must work on our own checkpoints
        ck = torch.load(c, map_location="cpu", weights_only=True)
        assert ck["meta"]["omnilidar"]["config"] == settings
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
    run_dir = root / "work" / summary["config_hash"]
    # Simulate a crash right after the iteration-2 checkpoint: a second work dir holding it only.
    work2 = root / "work2"
    run2 = work2 / summary["config_hash"]
    run2.mkdir(parents=True)
    (run2 / "iter_2.pth").write_bytes((run_dir / "iter_2.pth").read_bytes())
    (run2 / "last_checkpoint").write_text(str(run2 / "iter_2.pth"))
    resumed = train_generator(settings, index, prompts, work2, root / "ckpt2.pt", seed=3)
    assert resumed["iterations"] == 3
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


def test_changed_config_trains_in_a_new_work_dir(trained):
    from omnilidar.generator.training import config_hash

    settings = trained[1]
    other = json.loads(json.dumps(settings))
    other["training"]["lr"] *= 2
    longer = json.loads(json.dumps(settings))
    longer["training"]["iterations"] = 10
    longer["sampling"]["steps"] = 99
    assert config_hash(other, 3) != config_hash(settings, 3)
    assert config_hash(longer, 3) == config_hash(settings, 3)  # extending a run resumes it
    assert config_hash(settings, 4) != config_hash(settings, 3)


def _ema_gap(root, summary) -> float:
    """Distance between the final EMA weights and the raw weights of the last step."""
    final = torch.load(root / summary["out"], map_location="cpu", weights_only=True)["state_dict"]
    last = torch.load(sorted((root / "work" / summary["config_hash"]).glob("iter_*.pth"))[-1],
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
    warm_summary = train_generator(warm, index, prompts, root / "work", root / "ckpt_warm.pt", seed=3)
    gap_plain = _ema_gap(root, dict(summary, out="ckpt.pt"))
    gap_warm = _ema_gap(root, dict(warm_summary, out="ckpt_warm.pt"))
    assert gap_plain > 0 and gap_warm < 0.5 * gap_plain
