"""Seconds per scan of several sampler settings, timed side by side in one process.

Speed ratios between settings mean something only when every setting ran on the same device
under the same load. Timings recorded by separate sampling jobs (other runs, other neighbours on
the machine) do not; these do: the repeats go round the settings in turn, so a change of load
during the measurement falls on every setting alike, and each setting's figure is its median.
"""
from __future__ import annotations

import statistics
import time
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
    from omnilidar.generator.diffusion import generate, scan_seed
    from omnilidar.generator.schedule import CosineLogSNRSchedule
    from omnilidar.generator.unet import range_image_spec

    if batch < 1 or repeats < 1:
        raise ValueError(f"time_settings needs batch >= 1 and repeats >= 1, got {batch} and {repeats}")
    entry = prompt_cache["domains"][domain]

    def sample(s: TimedSetting, seeds: list[int], sampler: str, steps: int) -> None:
        cfg = s.payload["config"]
        schedule = CosineLogSNRSchedule(cfg["diffusion"]["logsnr_min"], cfg["diffusion"]["logsnr_max"])
        with torch.no_grad():  # the result comes back on the CPU: a GPU has finished when it returns
            generate(s.denoiser, s.payload["domains"].index(domain), entry["tokens"][0], entry["mask"][0], seeds,
                     range_image_spec(cfg).shape, sampler, steps, schedule, autocast_bf16=autocast_bf16)

    warmed = set()
    for s in settings:
        if id(s.denoiser) not in warmed:
            sample(s, [scan_seed(seed, domain, 0)], "ddim", 1)
            warmed.add(id(s.denoiser))
    runs: list[list[float]] = [[] for _ in settings]
    for r in range(repeats):
        seeds = [scan_seed(seed, domain, r * batch + i) for i in range(batch)]
        for s, times in zip(settings, runs):
            t0 = time.perf_counter()
            sample(s, seeds, s.sampler, s.steps)
            times.append((time.perf_counter() - t0) / batch)
    return [statistics.median(times) for times in runs]
