"""``distillation.lr_decay``: the student's learning rate, constant or annealed on a half cosine
within each phase (compression, every round), set per step from the step alone."""

from __future__ import annotations

import copy

import pytest
import torch

from omnilidar.generator.distill_steps import student_lr
from omnilidar.generator.training import train_generator
from test_generator_adversarial import resumes_inside_the_last_round
from test_generator_distill import _state, teacher  # noqa: F401  (the module's fixture)
from test_generator_fixtures import one_torch_thread  # noqa: F401


def _settings(decay: str, **distillation) -> dict:
    return {"model": {"base_channels": 16, "num_res_blocks": 2},
            "distillation": {"lr": 1e-4, "lr_decay": decay, "rounds": 2, "iterations_per_round": 4,
                             "compression_iterations": 4, "student_res_blocks": None, **distillation}}


def test_constant_keeps_the_rate_and_cosine_restarts_it_in_every_phase():
    assert [student_lr(_settings("constant"), i) for i in range(8)] == [1e-4] * 8
    rates = [student_lr(_settings("cosine"), i) / 1e-4 for i in range(8)]
    # no compression at the teacher's architecture: two rounds of 4 steps, each from lr down
    assert rates == pytest.approx([1.0, 0.8536, 0.5, 0.1464] * 2, abs=1e-4)
    pruned = [student_lr(_settings("cosine", student_res_blocks=1), i) / 1e-4 for i in range(12)]
    assert pruned == pytest.approx([1.0, 0.8536, 0.5, 0.1464] * 3, abs=1e-4)  # compression, then the rounds
    last = [student_lr(_settings("cosine", final_round_iterations=8), i) / 1e-4 for i in range(4, 12)]
    assert last[0] == 1.0 and last[4] == pytest.approx(0.5) and all(a > b for a, b in zip(last, last[1:]))


def test_a_cosine_distillation_steps_at_those_rates_and_resumes_to_the_same_student(teacher, tmp_path, monkeypatch):
    root, settings, index, prompts, _ = teacher
    decayed = copy.deepcopy(settings)
    decayed["distillation"]["lr_decay"] = "cosine"
    rates = []
    step = torch.optim.AdamW.step

    def recorded(self, *args, **kwargs):
        rates.append(self.param_groups[0]["lr"])
        return step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.AdamW, "step", recorded)
    state = resumes_inside_the_last_round(teacher, decayed, tmp_path)
    lr = settings["distillation"]["lr"]  # two rounds of two steps: lr, then half of it, in each
    assert rates[:4] == pytest.approx([lr, lr / 2, lr, lr / 2])
    constant = _state(root / "student.pt")
    assert not all(torch.equal(state[k], constant[k]) for k in state)


def test_with_a_second_network_only_the_student_s_rate_decays(teacher, tmp_path, monkeypatch):
    root, settings, index, prompts, _ = teacher
    decayed = copy.deepcopy(settings)
    decayed["distillation"].update(lr_decay="cosine", distribution_matching_weight=0.5)
    rates = {torch.optim.AdamW: [], torch.optim.Adam: []}
    steps = {cls: cls.step for cls in rates}

    def recorder(cls):
        def recorded(self, *args, **kwargs):
            if type(self) is cls:
                rates[cls].append(self.param_groups[0]["lr"])
            return steps[cls](self, *args, **kwargs)
        return recorded

    for cls in rates:
        monkeypatch.setattr(cls, "step", recorder(cls))
    train_generator(decayed, index, prompts, tmp_path / "work", tmp_path / "student.pt", seed=3,
                    teacher=root / "model.pt")
    lr = settings["distillation"]["lr"]
    assert rates[torch.optim.AdamW] == pytest.approx([lr, lr / 2, lr, lr / 2])  # the student's
    assert rates[torch.optim.Adam] == pytest.approx([decayed["distillation"]["critic_lr"]] * 2)  # the fake score's
