"""Samplers for the continuous logSNR schedule: DDPM ancestral, DDIM, DPM-Solver++ (2M).

All three share the diffusers-style interface: ``set_timesteps(n)`` fills
``timesteps`` (continuous t, from 1 down to 0 over ``linspace(1, 0, n + 1)``), and
``step(model_output, timestep, sample, generator)`` returns a
:class:`SchedulerOutput` with ``prev_sample`` and ``pred_original_sample``. The
model predicts epsilon; every step converts it to x0, clamps x0 to [-1, 1]
(``clip_sample``) and moves to the next time. The caller clamps the final sample.

Why not diffusers' schedulers directly: ``DDPMScheduler``, ``DDIMScheduler`` and
``DPMSolverMultistepScheduler`` all index a *discrete* training grid
(``alphas_cumprod`` of ``num_train_timesteps`` betas) and pick inference timesteps
as integers on it. Our model is trained at continuous t ~ U(0, 1) and conditioned
on logSNR(t) of the clipped cosine schedule (logSNR in [-15, 15]); forcing it onto
an integer grid would either change the schedule's end points (the discrete
cumulative product cannot reach logSNR = +15 at the first train step and -15 at
the last with a cosine spacing) or re-quantise the times the network sees, and
DDPM's posterior variance would come from betas we never trained with. The
updates below are the same algorithms written in continuous time (VDM's ancestral
posterior, DDIM's eta-family, Lu et al.'s DPM-Solver++ 2M in half-logSNR
lambda), with diffusers' naming so that swapping one for another is a one-line
change. ``tests/test_generator_samplers.py`` cross-checks our DDIM step against
diffusers' ``DDIMScheduler`` on a grid where both are defined.

Noise for the ancestral samplers comes from explicit ``torch.Generator`` objects:
one generator, or one per batch element (so a scan's result does not depend on
which other scans share its batch).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from omnilidar.generator.schedule import CosineLogSNRSchedule, predict_x0


@dataclass
class SchedulerOutput:
    """One sampler step: the sample at the next (less noisy) time and the x0 estimate."""

    prev_sample: torch.Tensor
    pred_original_sample: torch.Tensor


def _noise_like(sample: torch.Tensor, generator) -> torch.Tensor:
    if generator is None:
        raise ValueError("an ancestral sampler step needs an explicit torch.Generator")
    if isinstance(generator, (list, tuple)):
        if len(generator) != sample.shape[0]:
            raise ValueError(f"{len(generator)} generators for a batch of {sample.shape[0]}")
        return torch.stack(
            [torch.randn(sample.shape[1:], generator=g, device=g.device, dtype=torch.float32) for g in generator]
        ).to(sample.device)
    return torch.randn(sample.shape, generator=generator, device=generator.device, dtype=torch.float32).to(sample.device)


class ContinuousScheduler:
    """Base class: the time grid and per-step logSNR bookkeeping."""

    name = "base"

    def __init__(self, schedule: CosineLogSNRSchedule | None = None, clip_sample: bool = True):
        self.schedule = schedule or CosineLogSNRSchedule()
        self.clip_sample = clip_sample
        self.timesteps = torch.empty(0, dtype=torch.float64)
        self._grid = torch.empty(0, dtype=torch.float64)
        self._logsnr = torch.empty(0, dtype=torch.float64)
        self._step_index = 0

    @property
    def num_inference_steps(self) -> int:
        return len(self.timesteps)

    def set_timesteps(self, num_inference_steps: int, device: torch.device | str | None = None) -> None:
        """Use ``num_inference_steps`` uniform steps in t from 1 to 0."""
        n = int(num_inference_steps)
        if n < 1:
            raise ValueError(f"num_inference_steps must be >= 1, got {num_inference_steps}")
        self._grid = torch.linspace(1.0, 0.0, n + 1, dtype=torch.float64)
        self._logsnr = self.schedule.logsnr(self._grid)
        self.timesteps = self._grid[:-1].clone()
        self._step_index = 0
        self._reset_state()

    def _reset_state(self) -> None:
        pass

    def logsnr_at(self, timestep: float | torch.Tensor) -> torch.Tensor:
        """The logSNR the network is conditioned on at ``timestep``."""
        return self.schedule.logsnr(torch.as_tensor(timestep, dtype=torch.float64)).float()

    def _advance(self, timestep) -> tuple[float, float, int]:
        i = self._step_index
        if i >= self.num_inference_steps:
            raise RuntimeError("step() called more times than set_timesteps() allows")
        if abs(float(timestep) - float(self._grid[i])) > 1e-9:
            raise ValueError(f"expected timestep {float(self._grid[i])}, got {float(timestep)}")
        self._step_index += 1
        return float(self._logsnr[i]), float(self._logsnr[i + 1]), i

    def _x0(self, eps: torch.Tensor, sample: torch.Tensor, logsnr_t: float) -> torch.Tensor:
        return predict_x0(sample, eps, torch.tensor(logsnr_t), clamp=self.clip_sample).float()

    def step(self, model_output, timestep, sample, generator=None) -> SchedulerOutput:  # pragma: no cover
        raise NotImplementedError


def _alpha_sigma(logsnr: float) -> tuple[float, float]:
    # sqrt(sigmoid(l)) and sqrt(sigmoid(-l)) without overflow for |l| <= 15 (and beyond).
    return math.sqrt(1.0 / (1.0 + math.exp(-logsnr))), math.sqrt(1.0 / (1.0 + math.exp(logsnr)))


class DDPMScheduler(ContinuousScheduler):
    """Ancestral sampling from the exact posterior q(x_s | x_t, x0) (VDM, R2DM).

    With c = 1 - SNR(t)/SNR(s): mean = alpha_s ((1 - c) x_t / alpha_t + c x0),
    variance = c sigma_s^2. The last step (s = 0) adds no noise.
    """

    name = "ddpm"

    def step(self, model_output, timestep, sample, generator=None) -> SchedulerOutput:
        l_t, l_s, i = self._advance(timestep)
        x0 = self._x0(model_output, sample, l_t)
        a_t, _ = _alpha_sigma(l_t)
        a_s, s_s = _alpha_sigma(l_s)
        c = -math.expm1(l_t - l_s)
        mean = a_s * ((1.0 - c) / a_t * sample.float() + c * x0)
        if i + 1 < self.num_inference_steps:
            mean = mean + math.sqrt(c) * s_s * _noise_like(sample, generator)
        return SchedulerOutput(mean.to(sample.dtype), x0.to(sample.dtype))


class DDIMScheduler(ContinuousScheduler):
    """DDIM (Song et al. 2021) in continuous time; ``eta = 0`` is deterministic, ``eta = 1`` equals DDPM.

    x_s = alpha_s x0 + sqrt(sigma_s^2 - v) eps_hat + sqrt(v) z with v = eta^2 c sigma_s^2
    and eps_hat recomputed from the clamped x0.
    """

    name = "ddim"

    def __init__(self, schedule: CosineLogSNRSchedule | None = None, clip_sample: bool = True, eta: float = 0.0):
        super().__init__(schedule, clip_sample)
        if not 0.0 <= eta <= 1.0:
            raise ValueError(f"eta must be in [0, 1], got {eta}")
        self.eta = float(eta)

    def step(self, model_output, timestep, sample, generator=None) -> SchedulerOutput:
        l_t, l_s, i = self._advance(timestep)
        x0 = self._x0(model_output, sample, l_t)
        a_t, s_t = _alpha_sigma(l_t)
        a_s, s_s = _alpha_sigma(l_s)
        eps_hat = (sample.float() - a_t * x0) / s_t
        last = i + 1 == self.num_inference_steps
        var = 0.0 if last else self.eta**2 * -math.expm1(l_t - l_s) * s_s**2
        out = a_s * x0 + math.sqrt(max(s_s**2 - var, 0.0)) * eps_hat
        if var > 0.0:
            out = out + math.sqrt(var) * _noise_like(sample, generator)
        return SchedulerOutput(out.to(sample.dtype), x0.to(sample.dtype))


class DPMSolverPlusPlus2MScheduler(ContinuousScheduler):
    """DPM-Solver++ (2M), data prediction, multistep (Lu et al. 2022).

    In lambda = logSNR / 2 with h = lambda_s - lambda_t:
    x_s = (sigma_s / sigma_t) x_t - alpha_s expm1(-h) D, where D = x0 on the first
    and last step and D = (1 + 1/(2r)) x0_t - 1/(2r) x0_prev otherwise
    (r = h_prev / h). Deterministic.
    """

    name = "dpmpp_2m"

    def _reset_state(self) -> None:
        self._prev_x0: torch.Tensor | None = None
        self._prev_h: float | None = None

    def step(self, model_output, timestep, sample, generator=None) -> SchedulerOutput:
        l_t, l_s, i = self._advance(timestep)
        x0 = self._x0(model_output, sample, l_t)
        a_t, s_t = _alpha_sigma(l_t)
        a_s, s_s = _alpha_sigma(l_s)
        h = 0.5 * (l_s - l_t)
        last = i + 1 == self.num_inference_steps
        if self._prev_x0 is None or last or self._prev_h is None or self._prev_h <= 0:
            d = x0
        else:
            r = self._prev_h / h
            d = (1.0 + 0.5 / r) * x0 - (0.5 / r) * self._prev_x0
        out = (s_s / s_t) * sample.float() - a_s * math.expm1(-h) * d
        self._prev_x0, self._prev_h = x0, h
        return SchedulerOutput(out.to(sample.dtype), x0.to(sample.dtype))


SAMPLERS = {cls.name: cls for cls in (DDPMScheduler, DDIMScheduler, DPMSolverPlusPlus2MScheduler)}


def make_scheduler(name: str, schedule: CosineLogSNRSchedule | None = None, **kwargs) -> ContinuousScheduler:
    """Build a sampler by name: ``ddpm``, ``ddim`` or ``dpmpp_2m``."""
    try:
        cls = SAMPLERS[name]
    except KeyError:
        raise ValueError(f"unknown sampler {name!r}; choose from {sorted(SAMPLERS)}") from None
    return cls(schedule, **kwargs)
