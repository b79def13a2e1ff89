"""A distilled student's per-pixel return decision, calibrated on its teacher's samples.

A range image encodes a missing return as -1 and a return above the encoded minimum range. A
few-step student regresses x0, so where it cannot tell whether a pixel returns its estimate lands
between the two, above the minimum, and the pixel becomes a short-range point where its teacher
draws a drop-out (``benchmarks/measure_student_returns.py``: Drone and Beam32 students fill
drop-outs). ``generator.distillation.return_calibration`` N > 0 measures, after distillation, the
trained generator's return fraction per domain and image row on N seeded scans (DDIM on the
teacher's grid, the sampler the student learnt from) and the student's on the same noise, and sets
a per-row threshold on the student's encoded range: where the student draws more returns than its
teacher, its lowest values are drop-outs until the fractions agree. The thresholds travel in the
student's checkpoint (``return_thresholds``, (domains, rows)) and
:func:`omnilidar.generator.diffusion.apply_return_thresholds` applies them to every scan the student
samples. Calibration seeds are their own stream, so no
evaluation scan's noise is among them.
"""

from __future__ import annotations

import zlib

import numpy as np
import torch

from omnilidar.generator.data import rng_for
from omnilidar.generator.diffusion import generate
from omnilidar.generator.distill_steps import student_sampler, student_steps, teacher_sampler_steps

CALIBRATION_STREAM = 0xCA1B


def calibration_seeds(seed: int, domain: str, scans: int) -> list[int]:
    """Per-scan noise seeds of the calibration (four keys: never a sampling seed, which has three)."""
    return [int(rng_for(seed, zlib.crc32(domain.encode()), CALIBRATION_STREAM, i).integers(2**63 - 1))
            for i in range(scans)]


def row_thresholds(student_range: np.ndarray, student_returns: np.ndarray, teacher_returns: np.ndarray) -> np.ndarray:
    """(H,) encoded-range thresholds from the student's channel-0 values ``student_range`` (N, H, W)
    and the returns masks (N, H, W) of the student's and the teacher's scans on the same noise: in a
    row where the student returns more often, a value at or below the threshold is a drop-out, so
    that its fraction of returns is the teacher's; elsewhere -1 (nothing changes)."""
    n, h, w = student_range.shape
    out = np.full(h, -1.0, np.float32)
    for row in range(h):
        keep = int(round(float(teacher_returns[:, row].mean()) * n * w))
        if keep >= int(student_returns[:, row].sum()):
            continue
        values = np.sort(student_range[:, row].ravel())
        out[row] = values[n * w - keep - 1]  # the largest value that becomes a drop-out
    return out


def calibrate_returns(student: torch.nn.Module, teacher: torch.nn.Module, payload: dict, prompt_cache: dict,
                      seed: int, batch: int = 8, log=print) -> torch.Tensor:
    """(domains, H) float32 thresholds of ``student`` against ``teacher`` (the trained generator
    with DDIM x ``teacher_steps`` x ``teacher_substeps``, the sampler the student learnt, on the
    distillation's spacing) on ``return_calibration`` seeded scans per domain; ``payload``: the
    student's checkpoint contents (its settings, domains and their back-projection geometry)."""
    from omnilidar.data.range_image import decode
    from omnilidar.generator.sampling import domain_points_spec
    from omnilidar.generator.schedule import CosineLogSNRSchedule

    settings = payload["config"]
    distillation, d = settings["distillation"], settings["diffusion"]
    schedule = CosineLogSNRSchedule(d["logsnr_min"], d["logsnr_max"])
    scans, sampler = int(distillation["return_calibration"]), student_sampler(distillation)
    student, teacher = student.eval(), teacher.eval()
    out = []
    for index, name in enumerate(payload["domains"]):
        spec, entry = domain_points_spec(settings, payload, name), prompt_cache["domains"][name]
        seeds = calibration_seeds(seed, name, scans)
        sampled = {}
        for who, net, steps in (("teacher", teacher, teacher_sampler_steps(distillation)),
                                ("student", student, student_steps(distillation))):
            sampled[who] = np.concatenate([
                generate(net, index, entry["tokens"][0], entry["mask"][0], seeds[i:i + batch], spec.shape, sampler,
                         steps, schedule).numpy() for i in range(0, scans, batch)])
        returns = {who: np.stack([decode(img, spec)[2] for img in images]) for who, images in sampled.items()}
        out.append(row_thresholds(sampled["student"][:, 0], returns["student"], returns["teacher"]))
        log(f"return calibration {name}: returns {returns['teacher'].mean():.3f} (teacher), "
            f"{returns['student'].mean():.3f} (student), rows thresholded {int((out[-1] > -1).sum())}/{spec.shape[0]}")
    return torch.from_numpy(np.stack(out))
