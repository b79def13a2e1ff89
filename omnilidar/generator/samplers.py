"""Samplers for the continuous logSNR schedule: DDPM ancestral, DDIM, DPM-Solver++ (2M and 3M)
and UniPC (predictor-corrector, bh2), each on a choice of time-step spacings.

All share the diffusers-style interface: ``set_timesteps(n)`` fills ``timesteps``
(continuous t, from 1 down to 0 in ``n`` steps), and
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
posterior, DDIM's eta-family, Lu et al.'s DPM-Solver++ 2M / 3M and Zhao et al.'s UniPC in
half-logSNR lambda), with diffusers' naming so that swapping one for another is a one-line
change.

Time-step spacings (``spacing``): ``uniform`` in t (the default, as trained), ``logsnr``
uniform in logSNR (DPM-Solver's recommendation) and ``karras`` (Karras et al. 2022: rho = 7 in
sigma = exp(-logSNR / 2), denser near the data). A sampler name may carry its spacing as a
suffix: ``dpmpp_3m_karras``, ``unipc_logsnr``. ``tests/test_generator_samplers.py`` cross-checks our DDIM step against
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


SPACINGS = ("uniform", "logsnr", "karras")
KARRAS_RHO = 7.0


def time_grid(schedule: CosineLogSNRSchedule, n: int, spacing: str = "uniform", start: float = 1.0) -> torch.Tensor:
    """``n + 1`` times from ``start`` (1: pure noise) down to 0 (float64): uniform in t, uniform
    in logSNR, or Karras' rho-spacing of sigma = exp(-logSNR / 2) between logSNR(start) and the
    schedule's clean end."""
    if not 0.0 < start <= 1.0:
        raise ValueError(f"a time grid starts in (0, 1], got {start}")
    if spacing == "uniform":
        return torch.linspace(start, 0.0, n + 1, dtype=torch.float64)
    lo, hi = float(schedule.logsnr(torch.tensor(start, dtype=torch.float64))), schedule.logsnr_max
    if spacing == "logsnr":
        logsnr = torch.linspace(lo, hi, n + 1, dtype=torch.float64)
    else:
        ramp = torch.linspace(0.0, 1.0, n + 1, dtype=torch.float64)
        s_max, s_min = math.exp(-0.5 * lo) ** (1 / KARRAS_RHO), math.exp(-0.5 * hi) ** (1 / KARRAS_RHO)
        logsnr = -2.0 * KARRAS_RHO * torch.log(s_max + ramp * (s_min - s_max))
    grid = schedule.t_of_logsnr(logsnr)
    grid[0], grid[-1] = start, 0.0  # the ends exactly, whatever the rounding
    return grid


class ContinuousScheduler:
    """Base class: the time grid and per-step logSNR bookkeeping."""

    name = "base"

    def __init__(self, schedule: CosineLogSNRSchedule | None = None, clip_sample: bool = True,
                 spacing: str = "uniform"):
        if spacing not in SPACINGS:
            raise ValueError(f"unknown time-step spacing {spacing!r}; choose from {', '.join(SPACINGS)}")
        self.schedule = schedule or CosineLogSNRSchedule()
        self.clip_sample = clip_sample
        self.spacing = spacing
        self.timesteps = torch.empty(0, dtype=torch.float64)
        self._grid = torch.empty(0, dtype=torch.float64)
        self._logsnr = torch.empty(0, dtype=torch.float64)
        self._step_index = 0

    @property
    def num_inference_steps(self) -> int:
        return len(self.timesteps)

    def set_timesteps(self, num_inference_steps: int, device: torch.device | str | None = None,
                      start: float = 1.0) -> None:
        """Use ``num_inference_steps`` steps in t from ``start`` (1, or less to finish a partly
        noised image) to 0, spaced by ``self.spacing``."""
        n = int(num_inference_steps)
        if n < 1:
            raise ValueError(f"num_inference_steps must be >= 1, got {num_inference_steps}")
        self._grid = time_grid(self.schedule, n, self.spacing, start)
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

    def _exponential_step(self, model_output, timestep, sample):
        """What the exponential integrators (DPM-Solver++) share: the x0 estimate, the step h in
        lambda = logSNR / 2, alpha at the next time, sigma_next / sigma_now and whether it is the last."""
        l_t, l_s, i = self._advance(timestep)
        x0 = self._x0(model_output, sample, l_t)
        _, s_t = _alpha_sigma(l_t)
        a_s, s_s = _alpha_sigma(l_s)
        return x0, 0.5 * (l_s - l_t), a_s, s_s / s_t, i + 1 == self.num_inference_steps

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

    def __init__(self, schedule: CosineLogSNRSchedule | None = None, clip_sample: bool = True, eta: float = 0.0,
                 spacing: str = "uniform"):
        super().__init__(schedule, clip_sample, spacing)
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
        x0, h, a_s, ratio, last = self._exponential_step(model_output, timestep, sample)
        if self._prev_x0 is None or last or self._prev_h is None or self._prev_h <= 0:
            d = x0
        else:
            r = self._prev_h / h
            d = (1.0 + 0.5 / r) * x0 - (0.5 / r) * self._prev_x0
        out = ratio * sample.float() - a_s * math.expm1(-h) * d
        self._prev_x0, self._prev_h = x0, h
        return SchedulerOutput(out.to(sample.dtype), x0.to(sample.dtype))


class DPMSolverPlusPlus3MScheduler(ContinuousScheduler):
    """DPM-Solver++ (3M), data prediction, multistep, deterministic (Lu et al. 2022; the form of
    k-diffusion's ``dpmpp_3m``): first order on the first and last step, second order on the
    second, third order from the third on, from the last three x0 estimates."""

    name = "dpmpp_3m"

    def _reset_state(self) -> None:
        self._x0s: list[torch.Tensor] = []  # newest last
        self._hs: list[float] = []

    def step(self, model_output, timestep, sample, generator=None) -> SchedulerOutput:
        x0, h, a_s, ratio, last = self._exponential_step(model_output, timestep, sample)
        out = ratio * sample.float() - a_s * math.expm1(-h) * x0
        phi_2 = math.expm1(-h) / h + 1.0
        if not last and len(self._x0s) >= 2:
            r0, r1 = self._hs[-1] / h, self._hs[-2] / h
            d1_0 = (x0 - self._x0s[-1]) / r0
            d1_1 = (self._x0s[-1] - self._x0s[-2]) / r1
            d1 = d1_0 + (d1_0 - d1_1) * r0 / (r0 + r1)
            d2 = (d1_0 - d1_1) / (r0 + r1)
            phi_3 = phi_2 / h - 0.5
            out = out + a_s * (phi_2 * d1 - phi_3 * d2)
        elif not last and self._x0s:
            out = out + a_s * phi_2 * (x0 - self._x0s[-1]) / (self._hs[-1] / h)
        self._x0s = (self._x0s + [x0])[-2:]
        self._hs = (self._hs + [h])[-2:]
        return SchedulerOutput(out.to(sample.dtype), x0.to(sample.dtype))


class UniPCScheduler(ContinuousScheduler):
    """UniPC (Zhao et al. 2023), data prediction, B(h) = expm1(-h) ("bh2"), predictor of order
    up to ``order`` (2 by default) with the UniC corrector. The corrector refines the previous
    step's result with the model output at it, which the next step needs anyway: no extra network
    evaluation. No corrector after the last step (the final sample is never evaluated)."""

    name = "unipc"

    def __init__(self, schedule: CosineLogSNRSchedule | None = None, clip_sample: bool = True,
                 spacing: str = "uniform", order: int = 2):
        super().__init__(schedule, clip_sample, spacing)
        if order not in (1, 2, 3):
            raise ValueError(f"UniPC order must be 1, 2 or 3, got {order}")
        self.order = order

    def _reset_state(self) -> None:
        self._x0s: list[torch.Tensor] = []  # x0 estimates at the past grid points, newest last
        self._lams: list[float] = []  # their lambdas
        self._last_sample: torch.Tensor | None = None  # the previous step's input (before correction)

    @staticmethod
    def _coefficients(rks: list[float], hh: float, count: int) -> torch.Tensor:
        """The B(h) "bh2" solve of UniPC: rhos for ``count`` rows of the Vandermonde system."""
        h_phi_1 = math.expm1(hh)
        h_phi_k, factorial = h_phi_1 / hh - 1.0, 1
        rows, b = [], []
        for k in range(1, count + 1):
            rows.append([r ** (k - 1) for r in rks[:count]])
            b.append(h_phi_k * factorial / h_phi_1)
            factorial *= k + 1
            h_phi_k = h_phi_k / hh - 1.0 / factorial
        return torch.linalg.solve(torch.tensor(rows, dtype=torch.float64), torch.tensor(b, dtype=torch.float64))

    def _update(self, x, lam_from, lam_to, m0, history, new=None):
        """From ``x`` at ``lam_from`` (x0 estimate ``m0`` there, older estimates ``history`` as
        (lambda, x0)) to ``lam_to``; with ``new`` (the x0 estimate at ``lam_to``) the corrector."""
        h = lam_to - lam_from
        hh = -h
        a_to, s_to = _alpha_sigma(2.0 * lam_to)
        _, s_from = _alpha_sigma(2.0 * lam_from)
        b_h = math.expm1(hh)
        out = (s_to / s_from) * x - a_to * b_h * m0
        rks = [(lam - lam_from) / h for lam, _ in history] + [1.0]
        d1s = [(m - m0) / rk for (_, m), rk in zip(history, rks)]
        if new is None:  # predictor
            if d1s:
                rhos = [0.5] if len(d1s) == 1 else self._coefficients(rks, hh, len(d1s)).tolist()
                out = out - a_to * b_h * sum(r * d for r, d in zip(rhos, d1s))
            return out
        rhos = [0.5] if not d1s else self._coefficients(rks, hh, len(d1s) + 1).tolist()
        corr = sum((r * d for r, d in zip(rhos[:-1], d1s)), torch.zeros_like(m0))
        return out - a_to * b_h * (corr + rhos[-1] * (new - m0))

    def step(self, model_output, timestep, sample, generator=None) -> SchedulerOutput:
        l_t, l_s, i = self._advance(timestep)
        x0 = self._x0(model_output, sample, l_t)
        lam_t, lam_s = 0.5 * l_t, 0.5 * l_s
        x = sample.float()
        if self._last_sample is not None:  # UniC: correct the step that led here with x0 at t
            past = list(zip(self._lams, self._x0s))
            lam_prev, m_prev = past[-1]
            x = self._update(self._last_sample, lam_prev, lam_t, m_prev, past[-self.order:-1][::-1], new=x0)
        self._lams, self._x0s = (self._lams + [lam_t])[-self.order:], (self._x0s + [x0])[-self.order:]
        past = list(zip(self._lams, self._x0s))
        last = i + 1 == self.num_inference_steps
        # Lower order at the start (too little history) and on the last step (as DPM-Solver++).
        history = [] if last else past[:-1][::-1][: self.order - 1]
        out = self._update(x, lam_t, lam_s, x0, history)
        self._last_sample = x
        return SchedulerOutput(out.to(sample.dtype), x0.to(sample.dtype))


SAMPLERS = {cls.name: cls for cls in (DDPMScheduler, DDIMScheduler, DPMSolverPlusPlus2MScheduler,
                                      DPMSolverPlusPlus3MScheduler, UniPCScheduler)}
# Every name a config may give: a solver, optionally with its spacing as a suffix.
SAMPLER_NAMES = tuple(sorted(SAMPLERS) + [f"{n}_{sp}" for n in sorted(SAMPLERS) for sp in SPACINGS if sp != "uniform"])


def split_sampler_name(name: str) -> tuple[str, str]:
    """``dpmpp_3m_karras`` -> (``dpmpp_3m``, ``karras``); a bare solver name is uniform in t."""
    for spacing in SPACINGS:
        if name.endswith("_" + spacing) and name[: -len(spacing) - 1] in SAMPLERS:
            return name[: -len(spacing) - 1], spacing
    return name, "uniform"


def make_scheduler(name: str, schedule: CosineLogSNRSchedule | None = None, **kwargs) -> ContinuousScheduler:
    """Build a sampler by name: a solver (``ddpm``, ``ddim``, ``dpmpp_2m``, ``dpmpp_3m``,
    ``unipc``), optionally suffixed with its spacing (``_logsnr``, ``_karras``)."""
    solver, spacing = split_sampler_name(name)
    try:
        cls = SAMPLERS[solver]
    except KeyError:
        raise ValueError(f"unknown sampler {name!r}; choose from {', '.join(SAMPLER_NAMES)}") from None
    return cls(schedule, spacing=kwargs.pop("spacing", spacing), **kwargs)
