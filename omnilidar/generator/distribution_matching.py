"""Distribution matching for the last round of progressive distillation
(``distillation.distribution_matching_weight``), in the manner of distribution matching
distillation (DMD; Yin et al., 2024, and its two-time-scale successor DMD2).

A one-step student trained on an x0 regression alone learns the mean of what it cannot tell
apart, and a critic of its scans against the training scans (:mod:`omnilidar.generator.adversarial`)
pulls it towards the training scans rather than towards its teacher. Distribution matching pulls
the student's scans towards the trained generator's own distribution, the one the student must
match: a noised copy of each student scan is denoised twice, by the trained generator (the score
of its scans) and by a "fake score" network that keeps learning the student's current scans with
the generator's own denoising loss. Where the two x0 estimates differ, the student's scan lies
where the student puts more mass than its teacher; the difference estimates the gradient of the
KL divergence from the teacher's distribution to the student's, and the student descends it,
normalised per scan by the scan's mean distance to the teacher's estimate.

The fake score starts as a copy of the trained generator (so the term starts at 0) and trains
beside the student with an optimizer of its own. The term's weight is relative, as the critic's:
its gradient on the student's x0 is ``distribution_matching_weight`` times the regression's
(:func:`omnilidar.generator.distill.scaled_to_regression`).
"""

from __future__ import annotations

import copy

import torch

from omnilidar.generator.diffusion import epsilon_loss, noised
from omnilidar.generator.distill import scaled_to_regression
from omnilidar.generator.schedule import CosineLogSNRSchedule, predict_x0

# DMD draws the noise level away from both ends, where the two scores carry no information.
T_RANGE = (0.02, 0.98)


def build_fake_score(trained: torch.nn.Module) -> torch.nn.Module:
    """The fake score network: a trainable copy of the trained generator's denoiser."""
    return copy.deepcopy(trained).requires_grad_(True)


@torch.no_grad()
def matching_direction(trained: torch.nn.Module, fake: torch.nn.Module, x0: torch.Tensor, domain: torch.Tensor,
                       tokens: torch.Tensor, mask: torch.Tensor, schedule: CosineLogSNRSchedule,
                       generator: torch.Generator, extra: dict | None = None) -> torch.Tensor:
    """The direction in which the student's scans ``x0`` (clamped to the data range) move away from
    the trained generator's distribution: the fake score's x0 minus the trained generator's at one
    noised copy (t ~ U(T_RANGE), noise from ``generator``), per scan divided by the mean absolute
    distance of the scan to the trained generator's estimate."""
    extra = extra or {}
    sample = x0.detach().clamp(-1.0, 1.0).float()
    b = sample.shape[0]
    t = T_RANGE[0] + (T_RANGE[1] - T_RANGE[0]) * torch.rand(b, generator=generator, device=sample.device)
    eps = torch.randn(sample.shape, generator=generator, device=sample.device, dtype=torch.float32)
    z, logsnr = noised(sample, t, eps, schedule)
    real = predict_x0(z, trained(z, logsnr, domain, tokens, mask, **extra).float(), logsnr)
    fake_x0 = predict_x0(z, fake(z, logsnr, domain, tokens, mask, **extra).float(), logsnr)
    scale = (sample - real).abs().mean(dim=(1, 2, 3)).clamp(min=1e-6)
    return (fake_x0 - real) / scale[:, None, None, None]


def matching_loss(trained: torch.nn.Module, fake: torch.nn.Module, x0: torch.Tensor, domain: torch.Tensor,
                  tokens: torch.Tensor, mask: torch.Tensor, schedule: CosineLogSNRSchedule,
                  generator: torch.Generator, regression: torch.Tensor, weight: float,
                  extra: dict | None = None) -> torch.Tensor:
    """The student's distribution-matching term: its gradient on the (unclamped) ``x0`` is
    :func:`matching_direction`, scaled to ``weight`` times ``regression``'s gradient there. No
    network but the student gets a gradient from it."""
    direction = matching_direction(trained, fake, x0, domain, tokens, mask, schedule, generator, extra)
    term = 0.5 * (x0 - (x0 - direction).detach()).square().sum()
    return scaled_to_regression(term, x0, regression, weight)


def fake_score_loss(fake: torch.nn.Module, x0: torch.Tensor, domain: torch.Tensor, tokens: torch.Tensor,
                    mask: torch.Tensor, schedule: CosineLogSNRSchedule, gamma: float, generator: torch.Generator,
                    weighting: str = "min_snr", extra: dict | None = None) -> torch.Tensor:
    """The fake score's denoising loss (the trained generator's own) on the student's scans,
    clamped and detached: only the fake score learns from it."""
    columns = (extra or {}).get("columns")
    return epsilon_loss(fake, x0.detach().clamp(-1.0, 1.0), domain, tokens, mask, schedule, gamma, generator,
                        weighting=weighting, columns=columns)
