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

``generator.distillation.range_calibration`` K > 0 maps, on the same scans, the distribution of
the student's returned encoded ranges onto its teacher's, per domain and image row: K quantiles of
each (after the return decision) are the knots of a monotone piecewise-linear map
(``range_map``, (domains, rows, 2, K): student knots, teacher knots) that
:func:`omnilidar.generator.diffusion.apply_range_map` applies to the student's returns. A one-step
x0 regression pulls what it cannot place towards the mean, so far surfaces come nearer and one
row's ranges lie closer together than its teacher's (``benchmarks/measure_student_returns.py``).
``calibration_sectors`` S > 1 fits and applies both, the thresholds and the map, per row in each of
S equal azimuth sectors (column blocks; ``return_thresholds`` (domains, S, rows), ``range_map``
(domains, S, rows, 2, K)): where the sensor is pitched (Drone), a row looks down at the ground on
one side and up over the scene on the other, and one threshold or map per row mixes the two: the
row's lowest values, its near ground, become drop-outs where its teacher's drop-outs lie on the
other side.
"""

from __future__ import annotations

import zlib

import numpy as np
import torch

from omnilidar.generator.data import rng_for
from omnilidar.generator.diffusion import generate, sector_columns
from omnilidar.generator.distill_steps import calibration_samplers, student_sampler, student_steps

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


def row_range_knots(student_range: np.ndarray, student_returns: np.ndarray, teacher_range: np.ndarray,
                    teacher_returns: np.ndarray, knots: int) -> np.ndarray:
    """(H, 2, knots) float32: per image row, ``knots`` evenly spaced quantiles (0 to 1) of the
    student's returned encoded ranges and of the teacher's (channel-0 values and returns masks, each
    (N, H, W)). A row where either returns fewer than ``knots`` times keeps the identity map."""
    levels = np.linspace(0.0, 1.0, knots)
    out = np.tile(np.linspace(-1.0, 1.0, knots, dtype=np.float32), (student_range.shape[1], 2, 1))  # identity
    for row in range(student_range.shape[1]):
        own, theirs = student_range[:, row][student_returns[:, row]], teacher_range[:, row][teacher_returns[:, row]]
        if min(own.size, theirs.size) >= knots:
            out[row] = np.quantile(own, levels), np.quantile(theirs, levels)
    return out


def fit_by_sector(fit, arrays: tuple[np.ndarray, ...], sectors: int) -> np.ndarray:
    """``fit(*arrays)`` on each of ``sectors`` equal azimuth sectors (column blocks) of the (N, H, W)
    ``arrays`` on its own, stacked: (sectors, ...) per-row fits."""
    return np.stack([fit(*(a[..., cols] for a in arrays)) for cols in sector_columns(arrays[0].shape[-1], sectors)])


def calibration_scans(net: torch.nn.Module, payload: dict, prompt_cache: dict, domain: str, how: str, steps: int,
                      seed: int, batch: int = 8) -> np.ndarray:
    """The ``return_calibration`` scans (N, 2, H, W) of ``domain`` that ``net`` (the teacher or the
    student of ``payload``) draws with sampler ``how`` x ``steps`` on the calibration's own noise."""
    from omnilidar.generator.sampling import domain_points_spec
    from omnilidar.generator.schedule import CosineLogSNRSchedule

    settings = payload["config"]
    d, scans = settings["diffusion"], int(settings["distillation"]["return_calibration"])
    shape, entry = domain_points_spec(settings, payload, domain).shape, prompt_cache["domains"][domain]
    seeds, index = calibration_seeds(seed, domain, scans), payload["domains"].index(domain)
    schedule = CosineLogSNRSchedule(d["logsnr_min"], d["logsnr_max"])
    return np.concatenate([generate(net, index, entry["tokens"][0], entry["mask"][0], seeds[i:i + batch], shape, how,
                                    steps, schedule).numpy() for i in range(0, scans, batch)])


def calibrate_returns(student: torch.nn.Module, teacher: torch.nn.Module, payload: dict, prompt_cache: dict,
                      seed: int, choose=None, batch: int = 8, log=print) -> dict:
    """The student's calibration against ``teacher`` (the trained generator with DDIM x
    ``teacher_steps`` x ``teacher_substeps``, the sampler the student learnt, on the distillation's
    spacing, or with ``calibration_sampler``) on ``return_calibration`` seeded scans per domain:
    ``return_thresholds`` (domains, H) float32, and with ``range_calibration`` K > 0 ``range_map``
    (domains, H, 2, K) float32 of the thresholded student's returns (with ``calibration_sectors``
    S > 1 both per azimuth sector: (domains, S, H) and (domains, S, H, 2, K)); ``payload``: the student's checkpoint contents (its settings,
    domains and their back-projection geometry). With several candidate settings, ``choose(domain,
    {"sampler:steps": scans})`` -> (the one to calibrate on, its scores) decides per domain (the
    command passes :func:`omnilidar.metrics.generation.choose_on_training_scans`: by
    ``calibration_rule``, the candidate whose scans lie closest to the domain's training scans, or the
    first whose scans hold the best candidate of each metric there), and ``calibration_choice`` says which
    ({domain: "sampler:steps"})."""
    from omnilidar.data.range_image import decode
    from omnilidar.generator.sampling import domain_points_spec

    settings = payload["config"]
    distillation, sampler = settings["distillation"], student_sampler(settings["distillation"])
    candidates = calibration_samplers(distillation)
    if len(candidates) > 1 and choose is None:
        raise ValueError("several calibration candidates need a rule that chooses between them (choose)")
    knots = int(distillation.get("range_calibration") or 0)
    sectors = int(distillation.get("calibration_sectors") or 1)
    student, teacher = student.eval(), teacher.eval()
    out, maps, choice = [], [], {}
    for name in payload["domains"]:
        spec = domain_points_spec(settings, payload, name)

        def draw(net, how, steps):
            return calibration_scans(net, payload, prompt_cache, name, how, steps, seed, batch)

        drawn = {f"{how}:{steps}": draw(teacher, how, steps) for how, steps in candidates}
        choice[name] = next(iter(drawn))
        if len(drawn) > 1:
            choice[name], scores = choose(name, drawn)
            log(f"calibration candidates {name} against its training scans: "
                + ", ".join(f"{k} JSD {v['JSD']:.4f} MMD {v['MMD'] * 1e4:.2f}e-4" for k, v in scores.items())
                + f"; calibrated on {choice[name]}")
        sampled = {"teacher": drawn[choice[name]], "student": draw(student, sampler, student_steps(distillation))}
        returns = {who: np.stack([decode(img, spec)[2] for img in images]) for who, images in sampled.items()}
        thresholds = fit_by_sector(row_thresholds, (sampled["student"][:, 0], returns["student"], returns["teacher"]),
                                   sectors)  # (sectors, H)
        out.append(thresholds[0] if sectors == 1 else thresholds)
        log(f"return calibration {name}: returns {returns['teacher'].mean():.3f} (teacher), "
            f"{returns['student'].mean():.3f} (student), rows thresholded {int((thresholds > -1).sum())}/"
            f"{thresholds.size}" + (f" (rows x {sectors} azimuth sectors)" if sectors > 1 else ""))
        if knots:
            per_pixel = np.repeat(thresholds, spec.shape[1] // sectors, axis=0).T  # (H, W)
            kept = returns["student"] & (sampled["student"][:, 0] > per_pixel[None])
            fitted = fit_by_sector(lambda *a: row_range_knots(*a, knots),
                                   (sampled["student"][:, 0], kept, sampled["teacher"][:, 0], returns["teacher"]), sectors)
            maps.append(fitted[0] if sectors == 1 else fitted)
            mean = {who: float(sampled[who][:, 0][mask].mean()) for who, mask in
                    (("teacher", returns["teacher"]), ("student", kept))}
            log(f"range calibration {name}: mean encoded range of the returns {mean['teacher']:+.3f} (teacher), "
                f"{mean['student']:+.3f} (student)")
    calibration = {"return_thresholds": torch.from_numpy(np.stack(out)), "calibration_choice": choice}
    if knots:
        calibration["range_map"] = torch.from_numpy(np.stack(maps))
    return calibration
