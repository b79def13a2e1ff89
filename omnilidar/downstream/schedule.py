"""How long a downstream training runs, from its schedule and its scan counts alone (no torch, so
the workflow can count it when it plans jobs): ``schedule.iterations``, or ``epochs`` passes over
the mixed training set of :func:`omnilidar.downstream.seg.dataset.epoch_plan`."""

from __future__ import annotations

import math

from omnilidar.errors import InputError


def generated_per_epoch(num_real: int, num_generated: int, mixing: dict) -> int:
    """Generated scans in one epoch: ``concat`` takes each once; ``ratio`` takes enough that they
    make up ``generated_share`` of the epoch (all of them at a share of 1)."""
    if num_generated == 0:
        return 0
    if mixing["mode"] == "concat":
        return num_generated
    if mixing["mode"] == "ratio":
        share = float(mixing["generated_share"])
        return int(round(num_real * share / (1.0 - share))) if share < 1 else num_generated
    raise InputError(None, f"unknown mixing mode {mixing['mode']!r} (concat or ratio)")


def epoch_length(num_real: int, num_generated: int, mixing: dict) -> int:
    return num_real + generated_per_epoch(num_real, num_generated, mixing)


def total_iterations(schedule: dict, num_real: int, num_generated: int, mixing: dict) -> int:
    """Iterations of a run: ``schedule.iterations`` or ``epochs`` over the mixed set."""
    if schedule.get("iterations"):
        return int(schedule["iterations"])
    per_epoch = math.ceil(epoch_length(num_real, num_generated, mixing) / schedule["batch_size"])
    return int(schedule["epochs"]) * max(1, per_epoch)
