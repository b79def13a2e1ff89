"""OpenPCDet's detector optimisation: ``adam_onecycle`` (Adam with decoupled
weight decay under fastai's one-cycle learning-rate and momentum schedule) and
gradient-norm clipping at OPTIMIZATION.GRAD_NORM_CLIP.

OpenPCDet wraps Adam (betas 0.9, 0.99) in fastai's OptimWrapper with
``true_wd=True, bn_wd=True``: before every step each parameter, batch-norm ones
included, is scaled by ``1 - lr * wd``, then Adam steps without weight decay.
That is exactly torch's AdamW, which is used here. The schedule (OneCycle)
anneals with half cosines: lr from LR / DIV_FACTOR up to LR over the first
PCT_START of the steps, then down to LR / DIV_FACTOR / 1e4; Adam's beta1
follows MOMS from MOMS[0] to MOMS[1] and back.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from omnilidar.errors import InputError

OPTIMIZERS = ("adam_onecycle",)


def annealing_cos(start: float, end: float, pct: float) -> float:
    """Half-cosine from ``start`` (pct 0) to ``end`` (pct 1)."""
    return end + (start - end) / 2 * (math.cos(math.pi * pct) + 1)


class OneCycle:
    """Sets the optimizer's lr and beta1 for a given step (call before its update)."""

    def __init__(self, optimizer: torch.optim.Optimizer, total_steps: int, lr_max: float, moms, div_factor: float,
                 pct_start: float):
        if total_steps < 1:
            raise ValueError(f"one-cycle schedule needs at least one step, got {total_steps}")
        self.optimizer = optimizer
        self.total_steps = int(total_steps)
        low = lr_max / div_factor
        mid = int(pct_start * total_steps)
        self.lr_phases = [(0, mid, low, lr_max), (mid, self.total_steps, lr_max, low / 1e4)]
        self.mom_phases = [(0, mid, moms[0], moms[1]), (mid, self.total_steps, moms[1], moms[0])]
        self.step(0)

    @staticmethod
    def _value(phases, step: int) -> float:
        value = None
        for start, end, a, b in phases:
            if step >= start:  # a later phase that has begun wins, as OpenPCDet's LRSchedulerStep
                value = annealing_cos(a, b, (step - start) / max(end - start, 1))
        return value

    def step(self, step: int) -> None:
        lr, mom = self._value(self.lr_phases, step), self._value(self.mom_phases, step)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
            group["betas"] = (mom, group["betas"][1])

    __call__ = step

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:  # the schedule is a pure function of the step
        return None


def build_optimizer(model: nn.Module, optim_cfg: dict, total_steps: int, source: str = "OPTIMIZATION"):
    """(optimizer, schedule) for OpenPCDet's OPTIMIZATION section; call
    ``schedule.step(global_step)`` (or ``schedule(global_step)``) before each ``optimizer.step()``."""
    name = optim_cfg.get("OPTIMIZER")
    if name not in OPTIMIZERS:
        raise InputError(source, f"OPTIMIZER {name!r} is not supported (supported: {', '.join(OPTIMIZERS)})")
    return adam_onecycle(model, optim_cfg, total_steps)


def adam_onecycle(model: nn.Module, schedule: dict, total_steps: int):
    """(AdamW, OneCycle) from LR, WEIGHT_DECAY, MOMS, DIV_FACTOR, PCT_START; the keys
    may also be lower case (the workflow's ``schedule`` settings)."""
    optim_cfg = {str(k).upper(): v for k, v in schedule.items()}
    optimizer = torch.optim.AdamW(model.parameters(), lr=float(optim_cfg["LR"]), betas=(0.9, 0.99),
                                  weight_decay=float(optim_cfg.get("WEIGHT_DECAY", 0.0)))
    schedule = OneCycle(optimizer, total_steps, float(optim_cfg["LR"]), list(optim_cfg.get("MOMS", [0.95, 0.85])),
                        float(optim_cfg.get("DIV_FACTOR", 10)), float(optim_cfg.get("PCT_START", 0.4)))
    return optimizer, schedule


def clip_gradients(model: nn.Module, optim_cfg: dict) -> torch.Tensor:
    """Clip the total gradient norm to GRAD_NORM_CLIP (OpenPCDet default 10); returns the norm before clipping."""
    return nn.utils.clip_grad_norm_(model.parameters(), float(optim_cfg.get("GRAD_NORM_CLIP", 10.0)))
