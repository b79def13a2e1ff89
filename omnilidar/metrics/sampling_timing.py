"""Seconds per scan of several sampler settings, timed side by side in one process.

Speed ratios between settings mean something only when every setting ran on the same device
under the same load. Timings recorded by separate sampling jobs (other runs, other neighbours on
the machine) do not; these do: the repeats go round the settings in turn, so a change of load
during the measurement falls on every setting alike, and each setting's figure is its median.
"""
from __future__ import annotations

import statistics
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class TimedSetting:
    """One sampler setting to time: the network (a trained generator or a distilled student), its
    checkpoint payload, the solver and its steps."""
    denoiser: torch.nn.Module
    payload: dict
    sampler: str
    steps: int


def time_settings(settings: list[TimedSetting], prompt_cache: dict, domain: str, batch: int, repeats: int,
                  seed: int = 0, autocast_bf16: bool = False) -> list[float]:
    """Median wall-clock seconds per scan of each setting, sampling ``batch`` scans of ``domain``
    ``repeats`` times, round-robin over the settings. Each network first samples one untimed
    one-step scan, so lazy initialisation is charged to no setting."""
    from omnilidar.metrics.generation import sample_images
    from omnilidar.progress import ProgressLog

    if batch < 1 or repeats < 1:
        raise ValueError(f"time_settings needs batch >= 1 and repeats >= 1, got {batch} and {repeats}")
    warmed = set()
    for s in settings:
        if id(s.denoiser) not in warmed:
            sample_images(s.denoiser, s.payload, prompt_cache, domain, 1, "ddim", 1, seed, 1)
            warmed.add(id(s.denoiser))
    runs: list[list[float]] = [[] for _ in settings]
    progress = ProgressLog(repeats * sum(s.steps for s in settings), "timing, network evaluations")
    for r in range(repeats):
        for s, times in zip(settings, runs):
            times.append(sample_images(s.denoiser, s.payload, prompt_cache, domain, batch, s.sampler, s.steps,
                                       seed + r, batch, autocast_bf16)[1])
            progress.step(s.steps)
    return [statistics.median(times) for times in runs]
