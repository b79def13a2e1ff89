"""The adversarial term of the last distillation round: the critic, the fooling term's relative
weight, and a real tiny distillation with it (resume, provenance)."""

from __future__ import annotations

import copy
import shutil

import pytest
import torch

from omnilidar.errors import InputError
from omnilidar.generator.adversarial import build_critic, critic_loss, fooling_loss
from omnilidar.generator.checkpoint import load_generator
from omnilidar.generator.diffusion import generate
from omnilidar.generator.training import train_generator
from test_generator_distill import _first_prompt, _state, teacher  # noqa: F401
from test_generator_fixtures import one_torch_thread  # noqa: F401


def _last_checkpoint(work):
    last = sorted(work.rglob("iter_*.pth"), key=lambda p: int(p.stem.split("_")[1]))[-1]
    return torch.load(last, map_location="cpu", weights_only=False)


def test_the_fooling_gradient_is_the_set_fraction_of_the_regression_s_and_leaves_the_critic_alone():
    critic = build_critic(2, 3, seed=1)
    domain = torch.tensor([0, 2])
    x0 = (0.5 * torch.randn(2, 2, 8, 32, generator=torch.Generator().manual_seed(0))).requires_grad_(True)
    regression = (x0 - 0.1).square().mean()
    for weight in (0.1, 1.0):
        term = fooling_loss(critic, x0, domain, regression, weight)
        (g_fool,) = torch.autograd.grad(term, x0, retain_graph=True)
        (g_reg,) = torch.autograd.grad(regression, x0, retain_graph=True)
        assert torch.allclose(g_fool.norm(), weight * g_reg.norm(), rtol=1e-4)
    critic.zero_grad(set_to_none=True)
    fooling_loss(critic, x0, domain, regression, 1.0).backward()
    assert all(p.grad is None for p in critic.parameters()) and x0.grad is not None
    assert all(p.requires_grad for p in critic.parameters())
    # Every pixel outside the data range: the clamp passes no gradient and the term is zero, not NaN.
    far = torch.full_like(x0, 3.0, requires_grad=True)
    assert fooling_loss(critic, far, domain, (far - 0.1).square().mean(), 1.0).item() == 0.0


def test_the_critic_learns_to_tell_training_scans_from_the_student_s_and_only_it_learns():
    critic = build_critic(2, 2, seed=0)
    gen = torch.Generator().manual_seed(0)
    real = torch.where(torch.rand(8, 2, 8, 32, generator=gen) < 0.3, -1.0, 0.4)  # drop-outs and surfaces
    fake = (0.3 * torch.randn(8, 2, 8, 32, generator=gen) - 0.3).requires_grad_(True)  # the average of both
    domain = torch.tensor([0, 1] * 4)
    opt = torch.optim.Adam(critic.parameters(), lr=2e-3, betas=(0.0, 0.99))
    first = critic_loss(critic, real, fake, domain)
    for _ in range(60):
        opt.zero_grad()
        loss = critic_loss(critic, real, fake, domain)
        loss.backward()
        opt.step()
    assert fake.grad is None  # the fake is detached: only the critic learns from its loss
    assert loss.item() < 0.5 * first.item()


def test_the_critic_starts_from_its_seed():
    a, b, c = build_critic(2, 3, 5), build_critic(2, 3, 5), build_critic(2, 3, 6)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa) and not all(torch.equal(sa[k], sc[k]) for k in sa)


def _adversarial(settings, weight=0.5):
    s = copy.deepcopy(settings)
    s["distillation"]["adversarial_weight"] = weight
    return s


def distil_with_a_second_network(teacher, settings, tmp_path, losses):
    """A real tiny distillation with a last-round term over the finished plain one (in the
    teacher fixture's work dir): it starts afresh, ships a student without the second network,
    keeps that network and its own optimizer in the state, logs ``losses`` and samples. Returns
    (the last checkpoint, the student's loaded payload)."""
    root, _, index, prompts, _ = teacher
    shutil.copytree(root / "student_work", tmp_path / "work")  # the finished distillation without it
    summary = train_generator(settings, index, prompts, tmp_path / "work", tmp_path / "student.pt",
                              seed=3, teacher=root / "model.pt")
    assert summary["resumed_from"] == 0  # another loss is another distillation: it starts afresh
    plain, other = _state(root / "student.pt"), _state(tmp_path / "student.pt")
    assert plain.keys() == other.keys()  # the student ships without the second network
    assert not all(torch.equal(plain[k], other[k]) for k in plain)
    state = _last_checkpoint(tmp_path / "work")
    assert any(k.startswith("critic.") for k in state["state_dict"])  # the state keeps it to resume
    # Two optimizers: the student's as without a second network, that network's its own (rate, GAN betas).
    (student_group,), (critic_group,) = (state["optimizer"][k]["param_groups"] for k in ("denoiser", "critic"))
    assert student_group["lr"] == settings["distillation"]["lr"]
    assert critic_group["lr"] == settings["distillation"]["critic_lr"] and critic_group["betas"] == (0.0, 0.99)
    log = "\n".join(p.read_text() for p in (tmp_path / "work").rglob("*.log"))
    assert all(loss in log for loss in losses)
    den, payload = load_generator(tmp_path / "student.pt")
    assert len(student_group["params"]) == len(list(den.parameters())) and payload["student"]["steps"] == 1
    shape = tuple(settings["range_image"][k] for k in ("height", "width"))
    assert torch.isfinite(generate(den, 0, *_first_prompt(prompts), [1], shape, "ddim", 1)).all()
    return state, payload


def resumes_inside_the_last_round(teacher, settings, tmp_path) -> dict:
    """Distil ``settings`` whole, and again stopped inside the last round (student and second
    network both mid-way) and resumed: the same student bit for bit. Returns its state."""
    root, _, index, prompts, _ = teacher
    train_generator(settings, index, prompts, tmp_path / "whole", tmp_path / "whole.pt", seed=3,
                    teacher=root / "model.pt")
    train_generator(settings, index, prompts, tmp_path / "work", tmp_path / "seg.json", seed=3, until=3,
                    teacher=root / "model.pt")
    resumed = train_generator(settings, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                              teacher=root / "model.pt")
    assert resumed["resumed_from"] == 3
    a, b = _state(tmp_path / "whole.pt"), _state(tmp_path / "student.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)
    return a


def test_a_distillation_with_a_critic_trains_another_student_that_samples(teacher, tmp_path):
    _, payload = distil_with_a_second_network(teacher, _adversarial(teacher[1]), tmp_path,
                                              ("loss_critic", "loss_fooling"))
    assert payload["config"]["distillation"]["adversarial_weight"] == 0.5


def test_an_interrupted_distillation_with_a_critic_resumes_to_the_same_student(teacher, tmp_path):
    root, settings, index, prompts, _ = teacher
    a = resumes_inside_the_last_round(teacher, _adversarial(settings), tmp_path)
    # Another weight is another distillation: the finished state is not reused.
    other = train_generator(_adversarial(settings, 0.25), index, prompts, tmp_path / "work", tmp_path / "w.pt",
                            seed=3, teacher=root / "model.pt")
    assert other["resumed_from"] == 0
    c = _state(tmp_path / "w.pt")
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_a_critic_with_consistency_distillation_is_one_clear_error(teacher, tmp_path):
    root, settings, index, prompts, _ = teacher
    s = _adversarial(settings)
    s["distillation"]["method"] = "consistency"
    with pytest.raises(InputError, match="adversarial_weight.*progressive"):
        train_generator(s, index, prompts, tmp_path / "work", tmp_path / "s.pt", seed=3, teacher=root / "model.pt")
    assert not (tmp_path / "s.pt").exists()


def test_a_critic_on_several_processes_is_one_clear_error(teacher, tmp_path, monkeypatch):
    root, settings, index, prompts, _ = teacher
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(InputError, match="one process"):
        train_generator(_adversarial(settings), index, prompts, tmp_path / "work", tmp_path / "s.pt", seed=3,
                        teacher=root / "model.pt")
    assert not (tmp_path / "s.pt").exists()
