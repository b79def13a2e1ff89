"""An adversarial term for the last round of progressive distillation (``distillation.adversarial_weight``),
in the manner of adversarial diffusion distillation (Sauer et al., 2023).

A one-step student trained on an x0 regression alone learns the mean of what it cannot tell apart
(a drop-out and a return, a near and a far surface), and a per-pixel fix (a pseudo-Huber error, a
calibrated return decision) does not make its scans look like its teacher's as a set
(docs/results.md). A critic that tells the training scans from the student's one-step samples
gives the student a loss on the distribution of its scans instead: in the last round the student
minimises the regression plus the critic's hinge "fooling" term, the critic the hinge loss of
real against fake (the student's clamped x0, detached).

The critic is a small patch critic on range images (spectral-normalised convolutions, circular
in azimuth like the generator's) with a projection on the scan's domain, so each domain's scans
are told from that domain's training scans. The fooling term's weight is relative: its gradient on
the student's x0 is scaled to ``adversarial_weight`` times the regression's gradient norm there
(the adaptive weight of VQGAN, Esser et al., 2021, taken on the sample rather than a layer), so
the setting reads the same whatever the regression's scale at that time.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn.utils.parametrizations import spectral_norm

from omnilidar.generator.distill import scaled_to_regression


class _Conv(nn.Module):
    """A spectral-normalised convolution, padded circularly in azimuth and by zeros in elevation."""

    def __init__(self, cin: int, cout: int, kernel: int, stride: int = 1):
        super().__init__()
        self.pad = (kernel - 1) // 2
        self.conv = spectral_norm(nn.Conv2d(cin, cout, kernel, stride=stride, padding=0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = self.pad
        x = nn.functional.pad(x, (p, p, 0, 0), mode="circular")
        return self.conv(nn.functional.pad(x, (0, 0, p, p)))


class Critic(nn.Module):
    """Patch logits for range images of ``channels`` channels and ``num_domains`` domains: four
    convolutions at full, half and quarter resolution, then per location a linear logit plus the
    projection of the location's features on the domain's embedding."""

    def __init__(self, channels: int, num_domains: int, width: int = 32):
        super().__init__()
        self.body = nn.Sequential(
            _Conv(channels, width, 3), nn.LeakyReLU(0.2),
            _Conv(width, 2 * width, 4, stride=2), nn.LeakyReLU(0.2),
            _Conv(2 * width, 4 * width, 4, stride=2), nn.LeakyReLU(0.2),
            _Conv(4 * width, 4 * width, 3), nn.LeakyReLU(0.2),
        )
        self.logit = spectral_norm(nn.Conv2d(4 * width, 1, 1))
        self.embed = spectral_norm(nn.Embedding(num_domains, 4 * width))

    def forward(self, image: torch.Tensor, domain: torch.Tensor) -> torch.Tensor:
        h = self.body(image.float())
        projection = (h * self.embed(domain)[:, :, None, None]).sum(dim=1, keepdim=True)
        return self.logit(h) + projection


def build_critic(channels: int, num_domains: int, seed: int) -> Critic:
    """The critic, initialised from ``seed`` without touching the global random state."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        return Critic(channels, num_domains)


def critic_loss(critic: nn.Module, real: torch.Tensor, fake: torch.Tensor, domain: torch.Tensor) -> torch.Tensor:
    """The critic's hinge loss: logits above 1 on the training scans, below -1 on the student's
    (``fake`` is detached here, so only the critic learns from it)."""
    logits = critic(torch.cat([real, fake.detach()]), torch.cat([domain, domain]))
    real_logits, fake_logits = logits.split(real.shape[0])
    return torch.relu(1 - real_logits).mean() + torch.relu(1 + fake_logits).mean()


def fooling_loss(critic: nn.Module, x0: torch.Tensor, domain: torch.Tensor, regression: torch.Tensor,
                 weight: float) -> torch.Tensor:
    """The student's hinge fooling term -critic(x0 clamped to the data range), scaled so that its
    gradient on ``x0`` has ``weight`` times the norm of ``regression``'s there. The critic's
    parameters get no gradient from it."""
    critic.requires_grad_(False)
    try:
        fooling = -critic(x0.clamp(-1.0, 1.0), domain).mean()
    finally:
        critic.requires_grad_(True)
    return scaled_to_regression(fooling, x0, regression, weight)
