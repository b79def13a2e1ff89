"""``distillation.teacher_substeps``: the trained generator takes each of its teacher_steps in several
DDIM steps of a finer grid, so the student learns a more exact path of its ODE without another
halving. The grid, the targets' convergence, a real tiny distillation and the runtime estimate."""

from __future__ import annotations

import copy
import shutil

import pytest
import torch

from omnilidar.generator import training
from omnilidar.generator.distill import _grid_logsnr, consistency_loss, distillation_loss, progressive_pair
from omnilidar.generator.distill_steps import TEACHER_PASS_COST, teacher_sampler_steps, teacher_substep_extra_steps
from omnilidar.generator.samplers import SPACINGS
from omnilidar.generator.schedule import CosineLogSNRSchedule
from omnilidar.generator.training import train_generator
from test_generator_distill import PointMass, _state, teacher  # noqa: F401  (the module's fixture)
from test_generator_fixtures import one_torch_thread  # noqa: F401


@pytest.mark.parametrize("spacing", SPACINGS)
@pytest.mark.parametrize("substeps", [2, 3])
def test_the_finer_grid_holds_the_coarse_grid_s_times(spacing, substeps):
    schedule, n = CosineLogSNRSchedule(), 4
    index = torch.arange(n, 0, -1)
    fine = _grid_logsnr(schedule, n, spacing, index, range(0, 2 * substeps + 1, substeps), 2 * substeps)
    coarse = _grid_logsnr(schedule, n, spacing, index, (0, 1, 2))
    for f, c in zip(fine, coarse):
        torch.testing.assert_close(f, c, rtol=1e-9, atol=1e-9)
    # and the substeps lie strictly between them
    between = _grid_logsnr(schedule, n, spacing, index, (1,), 2 * substeps)[0]
    assert bool((between > coarse[0]).all() and (between < coarse[1]).all())


class Curved(torch.nn.Module):
    """A fixed smooth nonlinear denoiser: its DDIM path bends, so the step size matters."""

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(5)
        self.weight = torch.randn(2, 2, 3, 3, generator=g) * 0.3

    def forward(self, z, logsnr, domain, tokens, mask, columns=None):
        h = torch.nn.functional.conv2d(z, self.weight, padding=1)
        return torch.tanh(h + 0.5 * torch.sin(logsnr)[:, None, None, None] * z)


def _target(substeps, spacing):
    image = torch.rand(6, 2, 4, 8, generator=torch.Generator().manual_seed(2)) * 2 - 1
    args = (image, torch.zeros(6, dtype=torch.long), torch.zeros(6, 2, 5), torch.ones(6, 2, dtype=torch.bool),
            CosineLogSNRSchedule(), 2)
    net = Curved()
    return progressive_pair(net, net, *args, torch.Generator().manual_seed(1), spacing=spacing, substeps=substeps)[3]


@pytest.mark.parametrize("spacing", SPACINGS)
def test_more_substeps_teach_a_path_closer_to_the_teacher_s_ode(spacing):
    """The same draw (time, noise): the target moves, and towards the one of a fine solution."""
    reference = _target(64, spacing)
    errors = [float((_target(k, spacing) - reference).abs().mean()) for k in (1, 2, 4)]
    assert errors[0] > 1e-3  # the path bends: one DDIM step per half-step is not exact
    assert errors[0] > errors[1] > errors[2]


@pytest.mark.parametrize("method", ["progressive", "consistency"])
def test_the_exact_teacher_still_teaches_itself_in_substeps(method):
    c = torch.linspace(-0.5, 0.5, 2 * 4 * 8).reshape(1, 2, 4, 8)
    args = (c.expand(3, -1, -1, -1).clone(), torch.zeros(3, dtype=torch.long), torch.zeros(3, 2, 5),
            torch.ones(3, 2, dtype=torch.bool), CosineLogSNRSchedule(), 2)
    loss = distillation_loss if method == "progressive" else consistency_loss
    exact = PointMass(c)
    assert float(loss(exact, exact, *args, torch.Generator().manual_seed(1), substeps=3)) < 1e-5
    wrong = loss(PointMass(c + 0.1), exact, *args, torch.Generator().manual_seed(1), substeps=3)
    assert float(wrong) > 1e-4


def test_only_the_trained_generator_takes_substeps_in_a_real_distillation(teacher, tmp_path, monkeypatch):
    """Round 0 (the trained generator teaches) walks 3 substeps, round 1 (the student of round 0
    teaches, on its own grid) one; the student differs from one without substeps, records them,
    and a finished state of another setting is not resumed."""
    root, settings, index, prompts, _ = teacher
    seen = []
    real_loss = training.distillation_loss

    def recorded(*args, **kwargs):
        seen.append(kwargs["substeps"])
        return real_loss(*args, **kwargs)

    monkeypatch.setattr(training, "distillation_loss", recorded)
    finer = copy.deepcopy(settings)
    finer["distillation"]["teacher_substeps"] = 3
    shutil.copytree(root / "student_work", tmp_path / "work")  # the finished distillation without substeps
    summary = train_generator(finer, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                              teacher=root / "model.pt")
    assert summary["resumed_from"] == 0 and summary["iterations"] == 4
    assert seen == [3, 3, 1, 1]  # two rounds of two steps
    payload = torch.load(tmp_path / "student.pt", map_location="cpu", weights_only=True)
    assert payload["student"]["teacher_substeps"] == 3 and payload["student"]["steps"] == 1
    a, b = _state(root / "student.pt"), _state(tmp_path / "student.pt")
    assert not all(torch.equal(a[k], b[k]) for k in a)


def test_the_extra_cost_counts_the_teacher_s_further_passes():
    progressive = {"method": "progressive", "teacher_steps": 16, "rounds": 4, "iterations_per_round": 250,
                   "teacher_substeps": 4}
    assert teacher_sampler_steps(progressive) == 64
    # the first round's 250 steps, each 2 x 3 more teacher passes (measured: 3.1 s a step against 1.2 s)
    assert teacher_substep_extra_steps(progressive) == pytest.approx(250 * 6 * TEACHER_PASS_COST)
    assert 250 * (1 + 6 * TEACHER_PASS_COST) * 1.2 == pytest.approx(250 * 3.1, rel=0.05)
    assert teacher_substep_extra_steps({**progressive, "teacher_substeps": 1}) == 0
    consistency = {**progressive, "method": "consistency"}
    assert teacher_substep_extra_steps(consistency) == pytest.approx(1000 * 3 * TEACHER_PASS_COST)
