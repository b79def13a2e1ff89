"""Distribution matching in the last distillation round: the direction the student's scans move,
its relative weight, the fake score's loss, and a real tiny distillation with it (resume,
provenance, errors)."""

from __future__ import annotations

import copy

import pytest
import torch

from omnilidar.errors import InputError
from omnilidar.generator.distill_steps import LAST_ROUND_STEP_COST, distillation_iterations, last_round_extra_steps
from omnilidar.generator.distribution_matching import (build_fake_score, fake_score_loss, matching_direction,
                                                       matching_loss)
from omnilidar.generator.schedule import CosineLogSNRSchedule, alpha_sigma
from omnilidar.generator.training import train_generator
from test_generator_adversarial import distil_with_a_second_network, resumes_inside_the_last_round
from test_generator_distill import _state, teacher  # noqa: F401
from test_generator_fixtures import one_torch_thread  # noqa: F401

SCHEDULE = CosineLogSNRSchedule(-15.0, 15.0)
SHAPE = (2, 2, 8, 32)


class _Denoises(torch.nn.Module):
    """A denoiser whose x0 estimate is ``image`` whatever it is given (it returns that epsilon)."""

    def __init__(self, image: torch.Tensor):
        super().__init__()
        self.image = torch.nn.Parameter(image.clone())

    def forward(self, z, logsnr, domain, tokens, mask, **extra):
        alpha, sigma = (v[:, None, None, None] for v in alpha_sigma(logsnr))
        return (z - alpha * self.image) / sigma


def _args():
    return torch.tensor([0, 1]), torch.zeros(2, 3, 4), torch.ones(2, 3, dtype=torch.bool)


def test_the_student_s_scans_move_towards_the_trained_generator_s_and_away_from_its_own():
    trained_scan, student_scan = torch.full(SHAPE, 0.4), torch.full(SHAPE, -0.2)
    trained, fake = _Denoises(trained_scan), _Denoises(student_scan)  # the fake score has learnt the student
    x0 = student_scan.clone().requires_grad_(True)
    regression = (x0 - 0.1).square().mean()
    term = matching_loss(trained, fake, x0, *_args(), SCHEDULE, torch.Generator().manual_seed(0), regression, 1.0)
    (g,) = torch.autograd.grad(term, x0)
    stepped = x0.detach() - 0.1 * g / g.abs().max()  # one descent step on the term alone
    assert (stepped - trained_scan).abs().max() < (student_scan - trained_scan).abs().max()
    # A fake score that has learnt nothing yet (the trained generator's copy): no direction at all.
    copy_ = build_fake_score(trained)
    assert torch.equal(matching_direction(trained, copy_, x0, *_args(), SCHEDULE, torch.Generator().manual_seed(0)),
                       torch.zeros(SHAPE))
    assert all(p.requires_grad for p in copy_.parameters())


def test_the_matching_gradient_is_the_set_fraction_of_the_regression_s_and_only_the_student_learns():
    gen = torch.Generator().manual_seed(1)
    trained, fake = _Denoises(torch.rand(SHAPE, generator=gen) - 0.5), _Denoises(torch.rand(SHAPE, generator=gen))
    x0 = (0.5 * torch.randn(SHAPE, generator=gen)).requires_grad_(True)
    regression = (x0 - 0.1).square().mean()
    for weight in (0.1, 1.0):
        term = matching_loss(trained, fake, x0, *_args(), SCHEDULE, torch.Generator().manual_seed(2), regression, weight)
        (g_term,) = torch.autograd.grad(term, x0, retain_graph=True)
        (g_reg,) = torch.autograd.grad(regression, x0, retain_graph=True)
        assert torch.allclose(g_term.norm(), weight * g_reg.norm(), rtol=1e-4)
    matching_loss(trained, fake, x0, *_args(), SCHEDULE, torch.Generator().manual_seed(2), regression, 1.0).backward()
    assert trained.image.grad is None and fake.image.grad is None and x0.grad is not None


def test_the_fake_score_learns_from_the_student_s_scans_without_moving_them():
    gen = torch.Generator().manual_seed(3)
    fake = _Denoises(torch.zeros(SHAPE))
    x0 = (0.3 * torch.randn(SHAPE, generator=gen)).requires_grad_(True)
    loss = fake_score_loss(fake, x0, *_args(), SCHEDULE, 5.0, torch.Generator().manual_seed(4))
    loss.backward()
    assert x0.grad is None and fake.image.grad is not None and torch.isfinite(loss)
    # The same draws (seeded) give the same loss; another seed another.
    again = fake_score_loss(fake, x0, *_args(), SCHEDULE, 5.0, torch.Generator().manual_seed(4))
    other = fake_score_loss(fake, x0, *_args(), SCHEDULE, 5.0, torch.Generator().manual_seed(5))
    assert again.item() == loss.item() and other.item() != loss.item()


def _matching(settings, weight=0.5):
    s = copy.deepcopy(settings)
    s["distillation"]["distribution_matching_weight"] = weight
    return s


def test_a_distillation_with_distribution_matching_trains_another_student_that_samples(teacher, tmp_path):
    state, payload = distil_with_a_second_network(teacher, _matching(teacher[1]), tmp_path,
                                                  ("loss_critic", "loss_matching"))
    trained = _state(teacher[0] / "model.pt")
    fake = {k.removeprefix("critic."): v for k, v in state["state_dict"].items() if k.startswith("critic.")}
    assert fake.keys() == trained.keys()  # the fake score is the trained generator's network, in the state
    assert not all(torch.equal(fake[k], trained[k]) for k in trained)  # and it learnt the student's scans
    assert payload["config"]["distillation"]["distribution_matching_weight"] == 0.5


def test_distribution_matching_alone_in_the_last_round_trains_another_student(teacher, tmp_path):
    """last_round_regression_weight 0: the last round's student learns from the matching term alone
    (DMD2's choice); its regression is still logged, and the student differs from the one that
    also regresses (same seed, same draws)."""
    with_regression = _matching(teacher[1])
    alone = copy.deepcopy(with_regression)
    alone["distillation"]["last_round_regression_weight"] = 0.0
    distil_with_a_second_network(teacher, alone, tmp_path / "alone", ("loss_matching", "x0_regression"))
    distil_with_a_second_network(teacher, with_regression, tmp_path / "both", ("loss_matching", "x0_regression"))
    a, b = _state(tmp_path / "alone" / "student.pt"), _state(tmp_path / "both" / "student.pt")
    assert not all(torch.equal(a[k], b[k]) for k in a)


def test_an_interrupted_distillation_with_distribution_matching_resumes_to_the_same_student(teacher, tmp_path):
    resumes_inside_the_last_round(teacher, _matching(teacher[1]), tmp_path)


def test_a_longer_last_round_resumes_the_finished_distillation_at_a_constant_rate(teacher, tmp_path):
    """final_round_iterations extends a finished distillation as iterations extends a training: the
    longer last round resumes its state and ends on the student distilled whole at that length, bit
    for bit. Under a cosine rate the round's length shapes every rate in it: it starts afresh."""
    root, settings, index, prompts, _ = teacher
    short = _matching(settings)
    longer = copy.deepcopy(short)
    longer["distillation"]["final_round_iterations"] = short["distillation"]["iterations_per_round"] + 2
    train_generator(longer, index, prompts, tmp_path / "whole", tmp_path / "whole.pt", seed=3,
                    teacher=root / "model.pt")
    first = train_generator(short, index, prompts, tmp_path / "work", tmp_path / "short.pt", seed=3,
                            teacher=root / "model.pt")
    extended = train_generator(longer, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                               teacher=root / "model.pt")
    assert extended["resumed_from"] == distillation_iterations(short) == first["iterations"]
    a, b = _state(tmp_path / "whole.pt"), _state(tmp_path / "student.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)
    cosine = {**short, "distillation": {**short["distillation"], "lr_decay": "cosine"}}
    train_generator(cosine, index, prompts, tmp_path / "cosine", tmp_path / "c.pt", seed=3, teacher=root / "model.pt")
    cosine_longer = {**cosine, "distillation": {**cosine["distillation"], "final_round_iterations": 6}}
    again = train_generator(cosine_longer, index, prompts, tmp_path / "cosine", tmp_path / "c6.pt", seed=3,
                            teacher=root / "model.pt")
    assert again["resumed_from"] == 0


@pytest.mark.parametrize("change, message", [
    ({"method": "consistency"}, "distribution_matching_weight.*progressive"),
    ({"adversarial_weight": 0.5}, "set one of them"),
    # the regression weighed beside no last-round term at all
    ({"distribution_matching_weight": 0, "last_round_regression_weight": 0.0},
     "last_round_regression_weight 0.0.*distribution_matching_weight"),
])
def test_distribution_matching_that_cannot_run_is_one_clear_error(teacher, tmp_path, change, message):
    root, settings, index, prompts, _ = teacher
    s = _matching(settings)
    s["distillation"].update(change)
    with pytest.raises(InputError, match=message):
        train_generator(s, index, prompts, tmp_path / "work", tmp_path / "s.pt", seed=3, teacher=root / "model.pt")
    assert not (tmp_path / "s.pt").exists()


def test_the_fake_score_steps_critic_updates_times_per_student_step(teacher, tmp_path):
    root, settings, index, prompts, _ = teacher
    steps = {}
    work = tmp_path / "work"  # one work dir: another critic_updates over a finished state starts afresh
    for updates in (1, 2):
        s = _matching(settings)
        s["distillation"]["critic_updates"] = updates
        summary = train_generator(s, index, prompts, work, tmp_path / f"u{updates}.pt", seed=3,
                                  teacher=root / "model.pt")
        assert summary["resumed_from"] == 0
        state = torch.load(sorted(work.rglob("iter_*.pth"), key=lambda p: int(p.stem.split("_")[1]))[-1],
                           map_location="cpu", weights_only=False)["optimizer"]
        steps[updates] = {k: int(next(iter(state[k]["state"].values()))["step"]) for k in ("denoiser", "critic")}
    last_round = settings["distillation"]["iterations_per_round"]
    assert steps[1]["critic"] == last_round and steps[2]["critic"] == 2 * last_round
    assert steps[1]["denoiser"] == steps[2]["denoiser"]  # the student steps as often either way


def test_the_last_round_s_second_network_is_counted_per_update_in_the_runtime_estimate():
    d = {"rounds": 3, "iterations_per_round": 4, "final_round_iterations": 10, "distribution_matching_weight": 1.0}
    first, each = LAST_ROUND_STEP_COST["distribution_matching_weight"]
    assert last_round_extra_steps(d) == pytest.approx(10 * (first - 1))  # the last round only, one update
    assert last_round_extra_steps({**d, "critic_updates": 3}) == pytest.approx(10 * (first - 1 + 2 * each))
    assert last_round_extra_steps({**d, "distribution_matching_weight": 0}) == 0
