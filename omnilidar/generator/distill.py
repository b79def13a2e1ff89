"""Distillation of the generator into a few-step student: progressive distillation (Salimans &
Ho, 2022; ``distillation.method: progressive``, the default) or consistency distillation (Song et
al., 2023; ``consistency``), at the same budget of optimizer steps and sampled alike.

Each round halves the number of deterministic DDIM steps: the student learns to cover in one step
what the round's teacher covers in two. The steps lie on a grid uniform in t (the default), in
logSNR or Karras' sigma spacing (``distillation.spacing``, the samplers' ``time_grid``); the
student samples with DDIM on the same spacing. Round 0's teacher is the trained
generator sampling in ``teacher_steps``; every later round's teacher is the student as the
previous round left it. After ``rounds`` rounds the student samples in
``teacher_steps / 2**rounds`` DDIM steps with the same conditioning (prompt tokens and domain).

Why progressive distillation is the default: measured against consistency distillation at the
same budget and the same single step on all eight domains (docs/generator.md), its student holds
the teacher on more domains with lower FRD and FRID. It keeps the generator's parameterisation,
schedule and sampler (the student is a generator checkpoint sampled with DDIM), every round has an
exact regression target, and unlike rectified-flow reflow it needs no teacher-generated data set
up front (reflow must first sample the teacher for every training pair, which at paper scale
costs about as much as the 80,000 scans it would save).

In continuous time with student step 1/N: t ~ {1/N, ..., 1}, t' = t - 1/(2N), t'' = t - 1/N.
The teacher's two DDIM steps z_t -> z_t' -> z_t'' give the x0 target that one DDIM step from
z_t must use to land on z_t''::

    x~ = (z_t'' - (sigma_t'' / sigma_t) z_t) / (alpha_t'' - (sigma_t'' / sigma_t) alpha_t)

The loss is the x0 error weighted by max(SNR(t), 1) ("truncated SNR" weighting), per pixel squared
(the default) or pseudo-Huber (``distillation.huber_c``). A squared error is minimised by the mean
of what the student cannot tell apart, so a one-step student averages it (a drop-out and a return,
a near and a far surface); a pseudo-Huber error above ``huber_c`` is minimised by the median,
which picks one of them.

Consistency distillation, for the measured comparison: the student's x0 estimate f(z_t, t) is
trained to agree with its own estimate one teacher step later, f(z_s, s), where z_s is the frozen
trained generator's DDIM step from z_t on the grid of ``teacher_steps`` (t = n / N, s = t - 1/N);
at s = 0 the target is z_s itself (the boundary condition f(z, 0) = z). The target is the
student's own estimate without gradient (the improved-consistency-training choice of no EMA
target network). It trains the rounds' steps, the progressive budget, and
the student samples in the same ``teacher_steps / 2^rounds`` DDIM steps.
"""

from __future__ import annotations

import torch

from omnilidar.generator.diffusion import azimuth_windows, take_columns
from omnilidar.generator.samplers import time_grid
from omnilidar.generator.schedule import CosineLogSNRSchedule, alpha_sigma, predict_x0


def _per_scan(v: torch.Tensor) -> torch.Tensor:
    return v[:, None, None, None]


def ddim_move(x0: torch.Tensor, z_t: torch.Tensor, logsnr_t: torch.Tensor, logsnr_s: torch.Tensor) -> torch.Tensor:
    """One deterministic DDIM step from time t to s (per scan), given the x0 estimate."""
    a_t, s_t = alpha_sigma(logsnr_t.double())
    a_s, s_s = alpha_sigma(logsnr_s.double())
    eps_hat = (z_t.double() - _per_scan(a_t) * x0.double()) / _per_scan(s_t)
    return (_per_scan(a_s) * x0.double() + _per_scan(s_s) * eps_hat).float()


def two_step_target(z_t: torch.Tensor, z_target: torch.Tensor, logsnr_t: torch.Tensor,
                    logsnr_target: torch.Tensor) -> torch.Tensor:
    """The x0 with which one DDIM step from z_t lands exactly on ``z_target``."""
    a_t, s_t = alpha_sigma(logsnr_t.double())
    a_u, s_u = alpha_sigma(logsnr_target.double())
    ratio = s_u / s_t
    return ((z_target.double() - _per_scan(ratio) * z_t.double()) / _per_scan(a_u - ratio * a_t)).float()


def _draw(image: torch.Tensor, steps: int, generator: torch.Generator, crop_width: int | None):
    """Azimuth windows (when training on them), a step index in 1..steps and the noise, drawn in
    that order: (the windowed image, the denoiser's extra arguments, index, noise)."""
    b = image.shape[0]
    extra = {}
    if crop_width is not None and crop_width < image.shape[-1]:
        columns = azimuth_windows(image.shape[-1], crop_width, b, generator, image.device)
        image = take_columns(image, columns)
        extra = {"columns": columns}
    index = torch.randint(1, steps + 1, (b,), generator=generator, device=image.device)
    eps = torch.randn(image.shape, generator=generator, device=image.device, dtype=torch.float32)
    return image, extra, index, eps


def _grid_logsnr(schedule: CosineLogSNRSchedule, steps: int, spacing: str, index: torch.Tensor,
                 points, parts: int = 2) -> list[torch.Tensor]:
    """logSNR at step ``index`` (1..steps, counted from the data end) of a ``steps``-step DDIM grid of
    ``spacing`` (:func:`omnilidar.generator.samplers.time_grid`), moved on by each of ``points``
    ``1 / parts`` steps towards the data: with ``parts`` 2, (0,) is the step's start, (0, 1, 2) its
    start, midpoint and end. The finer grid holds the coarse one's times (every spacing is a
    uniform ramp in t, logSNR or sigma^(1/rho))."""
    grid = time_grid(schedule, parts * steps, spacing).to(index.device)
    start = parts * (steps - index)
    return [schedule.logsnr(grid[start + h]) for h in points]


def teacher_walk(teacher: torch.nn.Module, z: torch.Tensor, logsnrs: list[torch.Tensor], domain: torch.Tensor,
                 tokens: torch.Tensor, mask: torch.Tensor, extra: dict) -> torch.Tensor:
    """The teacher's deterministic DDIM steps from ``z`` at ``logsnrs[0]`` through each later logSNR
    (per scan): where it lands at the last one."""
    for l_from, l_to in zip(logsnrs[:-1], logsnrs[1:]):
        z = ddim_move(predict_x0(z, teacher(z, l_from, domain, tokens, mask, **extra), l_from), z, l_from, l_to)
    return z


def _noised(image: torch.Tensor, eps: torch.Tensor, logsnr: torch.Tensor) -> torch.Tensor:
    """z_t = alpha_t x0 + sigma_t eps (per scan, in double precision)."""
    a_t, s_t = alpha_sigma(logsnr)
    return (_per_scan(a_t) * image.double() + _per_scan(s_t) * eps.double()).float()


def pixel_error(diff: torch.Tensor, huber_c: float | None = None) -> torch.Tensor:
    """Per-pixel error of an x0 difference: squared (``huber_c`` None), or pseudo-Huber
    sqrt(d^2 + c^2) - c, which is quadratic below c and grows like |d| above it."""
    if huber_c is None:
        return diff.square()
    return torch.sqrt(diff.square() + huber_c**2) - huber_c


def weighted_x0_error(x0: torch.Tensor, logsnr: torch.Tensor, target: torch.Tensor,
                      huber_c: float | None = None) -> torch.Tensor:
    """An x0 estimate against ``target``, weighted by max(SNR, 1) ("truncated SNR"), per pixel
    squared or pseudo-Huber (:func:`pixel_error`)."""
    weight = torch.clamp(torch.exp(logsnr.double()), min=1.0).float()
    return (weight * pixel_error(x0 - target, huber_c).mean(dim=(1, 2, 3))).mean()


def scaled_to_regression(term: torch.Tensor, x0: torch.Tensor, regression: torch.Tensor,
                         weight: float) -> torch.Tensor:
    """``term`` scaled so that its gradient on the student's ``x0`` has ``weight`` times the norm of
    ``regression``'s there (the adaptive weight of VQGAN, Esser et al., 2021, taken on the sample
    rather than a layer): a setting that reads the same whatever the regression's scale. A term
    with no gradient on ``x0`` (every pixel clamped) contributes 0."""
    (g_regression,) = torch.autograd.grad(regression, x0, retain_graph=True)
    (g_term,) = torch.autograd.grad(term, x0, retain_graph=True)
    norm = g_term.norm()
    if not torch.isfinite(norm) or norm == 0:
        return term * 0.0
    return term * (weight * g_regression.norm() / norm).detach()


def _weighted_x0_error(student_out: torch.Tensor, z_t: torch.Tensor, logsnr: torch.Tensor,
                       target: torch.Tensor, huber_c: float | None = None) -> torch.Tensor:
    """:func:`weighted_x0_error` of the student's (unclamped) x0 from its network output."""
    return weighted_x0_error(predict_x0(z_t, student_out.float(), logsnr, clamp=False), logsnr, target, huber_c)


def progressive_pair(student: torch.nn.Module, teacher: torch.nn.Module, image: torch.Tensor, domain: torch.Tensor,
                     tokens: torch.Tensor, mask: torch.Tensor, schedule: CosineLogSNRSchedule, steps: int,
                     generator: torch.Generator, crop_width: int | None = None, spacing: str = "uniform",
                     substeps: int = 1):
    """One draw of progressive distillation: (the training scans, windowed where training crops,
    the denoiser's extra arguments for those windows, the ``steps``-step student's unclamped x0 at
    a grid time t, the x0 with which its one DDIM step lands where two teacher steps do, logSNR at t).
    With ``substeps`` k the teacher takes each of its two steps in k DDIM steps of a k times finer
    grid: the student learns a more exact path of the teacher's ODE at 2k teacher evaluations.

    Noise, times and azimuth windows come from ``generator`` in the order of
    :func:`omnilidar.generator.diffusion.epsilon_loss` (windows, time, noise)."""
    image, extra, index, eps = _draw(image, steps, generator, crop_width)
    grid = _grid_logsnr(schedule, steps, spacing, index, range(2 * substeps + 1), 2 * substeps)
    z_t = _noised(image, eps, grid[0])
    logsnrs = [l.float() for l in grid]
    l_t, l_end = logsnrs[0], logsnrs[-1]
    with torch.no_grad():
        target = two_step_target(z_t, teacher_walk(teacher, z_t, logsnrs, domain, tokens, mask, extra), l_t, l_end)
    x0 = predict_x0(z_t, student(z_t, l_t, domain, tokens, mask, **extra).float(), l_t, clamp=False)
    return image, extra, x0, target, l_t


def distillation_loss(student: torch.nn.Module, teacher: torch.nn.Module, image: torch.Tensor, domain: torch.Tensor,
                      tokens: torch.Tensor, mask: torch.Tensor, schedule: CosineLogSNRSchedule, steps: int,
                      generator: torch.Generator, crop_width: int | None = None,
                      spacing: str = "uniform", huber_c: float | None = None, substeps: int = 1) -> torch.Tensor:
    """Truncated-SNR weighted x0 error of the ``steps``-step student against two teacher steps
    (drawn as :func:`progressive_pair` draws)."""
    _, _, x0, target, l_t = progressive_pair(student, teacher, image, domain, tokens, mask, schedule, steps, generator,
                                          crop_width, spacing, substeps)
    return weighted_x0_error(x0, l_t, target, huber_c)


def compression_loss(student: torch.nn.Module, teacher: torch.nn.Module, image: torch.Tensor, domain: torch.Tensor,
                     tokens: torch.Tensor, mask: torch.Tensor, schedule: CosineLogSNRSchedule, grid: int,
                     generator: torch.Generator, crop_width: int | None = None,
                     spacing: str = "uniform", huber_c: float | None = None) -> torch.Tensor:
    """Truncated-SNR weighted error between the student's x0 and the teacher's at the times of a
    ``grid``-step DDIM sampler: one step of the student lands where one of the teacher lands, so a
    narrower student starts its rounds as a copy of the trained generator's sampler. Draws as
    :func:`distillation_loss` does."""
    image, extra, index, eps = _draw(image, grid, generator, crop_width)
    (l_t,) = _grid_logsnr(schedule, grid, spacing, index, (0,))
    z_t = _noised(image, eps, l_t)
    l_t = l_t.float()
    with torch.no_grad():
        target = predict_x0(z_t, teacher(z_t, l_t, domain, tokens, mask, **extra).float(), l_t)
    return _weighted_x0_error(student(z_t, l_t, domain, tokens, mask, **extra), z_t, l_t, target, huber_c)


def consistency_loss(student: torch.nn.Module, teacher: torch.nn.Module, image: torch.Tensor, domain: torch.Tensor,
                     tokens: torch.Tensor, mask: torch.Tensor, schedule: CosineLogSNRSchedule, grid: int,
                     generator: torch.Generator, crop_width: int | None = None,
                     spacing: str = "uniform", huber_c: float | None = None, substeps: int = 1) -> torch.Tensor:
    """Truncated-SNR weighted error between the student's x0 at t and its own x0 (no gradient) one
    teacher DDIM step later on a ``grid``-step grid (taken in ``substeps`` DDIM steps of a finer
    grid); at s = 0 the target is the teacher's landing.

    Noise, times and azimuth windows come from ``generator`` in the order of
    :func:`distillation_loss` (windows, time, noise)."""
    image, extra, index, eps = _draw(image, grid, generator, crop_width)
    times = _grid_logsnr(schedule, grid, spacing, index, range(0, 2 * substeps + 1, 2), 2 * substeps)
    z_t = _noised(image, eps, times[0])
    logsnrs = [l.float() for l in times]
    l_t, l_s = logsnrs[0], logsnrs[-1]
    with torch.no_grad():
        z_s = teacher_walk(teacher, z_t, logsnrs, domain, tokens, mask, extra)
        target = predict_x0(z_s, student(z_s, l_s, domain, tokens, mask, **extra).float(), l_s)
        target = torch.where(_per_scan(index == 1), z_s.clamp(-1.0, 1.0), target)  # f(z, 0) = z
    return _weighted_x0_error(student(z_t, l_t, domain, tokens, mask, **extra), z_t, l_t, target, huber_c)
