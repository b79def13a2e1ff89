"""Diffusion on range images: the training objective and the reverse (sampling) loop.

Continuous time t in [0, 1] with a cosine log-SNR schedule
(:mod:`omnilidar.generator.schedule`); the denoiser predicts epsilon. Training noises
a clean batch at t ~ U(0, 1) and weights the epsilon error per scan by min-SNR-gamma;
sampling runs a diffusers-style scheduler (:mod:`omnilidar.generator.samplers`) from
per-scan seeded noise. The mmengine trainer and the sharded sampler are thin
adapters around these two functions.
"""

from __future__ import annotations

import zlib

import torch

from omnilidar.generator.data import rng_for
from omnilidar.generator.samplers import make_scheduler
from omnilidar.generator.schedule import CosineLogSNRSchedule, alpha_sigma, min_snr_weight


def noised(image: torch.Tensor, t: torch.Tensor, eps: torch.Tensor, schedule: CosineLogSNRSchedule):
    """x_t = alpha(t) x_0 + sigma(t) eps, and the log-SNR at t."""
    logsnr = schedule.logsnr(t)
    alpha, sigma = alpha_sigma(logsnr)
    return alpha[:, None, None, None] * image.float() + sigma[:, None, None, None] * eps, logsnr


def epsilon_loss(denoiser: torch.nn.Module, image: torch.Tensor, domain: torch.Tensor, tokens: torch.Tensor,
                 mask: torch.Tensor, schedule: CosineLogSNRSchedule, gamma: float,
                 generator: torch.Generator) -> torch.Tensor:
    """Min-SNR-gamma weighted epsilon MSE of one batch at t ~ U(0, 1); t and epsilon come from ``generator``."""
    b = image.shape[0]
    t = torch.rand(b, generator=generator, device=image.device, dtype=torch.float32)
    eps = torch.randn(image.shape, generator=generator, device=image.device, dtype=torch.float32)
    x_t, logsnr = noised(image, t, eps, schedule)
    pred = denoiser(x_t, logsnr, domain, tokens, mask)
    per_scan = (pred.float() - eps).square().mean(dim=(1, 2, 3))
    return (min_snr_weight(logsnr, gamma) * per_scan).mean()


@torch.no_grad()
def generate(
    denoiser: torch.nn.Module,
    domain_index: int,
    tokens: torch.Tensor,
    mask: torch.Tensor,
    seeds: list[int],
    shape: tuple[int, int],
    sampler: str = "dpmpp_2m",
    steps: int = 20,
    schedule: CosineLogSNRSchedule | None = None,
    ddim_eta: float = 0.0,
    autocast_bf16: bool = False,
) -> torch.Tensor:
    """Sample one batch: len(seeds) range images (B, 2, H, W) in [-1, 1], float32 on CPU.

    ``tokens`` (T, D) and ``mask`` (T,) are the domain's (first) prompt.
    """
    device = next(denoiser.parameters()).device
    kwargs = {"eta": ddim_eta} if sampler == "ddim" else {}
    sched = make_scheduler(sampler, schedule or CosineLogSNRSchedule(), **kwargs)
    sched.set_timesteps(steps)
    gens = []
    for s in seeds:
        g = torch.Generator(device=device)
        g.manual_seed(s)
        gens.append(g)
    b = len(seeds)
    x = torch.stack([torch.randn((2, *shape), generator=g, device=device) for g in gens])
    dom = torch.full((b,), int(domain_index), dtype=torch.long, device=device)
    tok = tokens.to(device).float().expand(b, -1, -1)
    msk = mask.to(device).bool().expand(b, -1)
    for t in sched.timesteps:
        logsnr = sched.logsnr_at(t).to(device).expand(b)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast_bf16):
            eps = denoiser(x, logsnr, dom, tok, msk)
        eps = torch.nan_to_num(eps.float(), nan=0.0, posinf=0.0, neginf=0.0)
        x = sched.step(eps, t, x, generator=gens).prev_sample
    return x.clamp(-1.0, 1.0).float().cpu()


def scan_seed(seed: int, domain: str, index: int) -> int:
    """The per-scan seed of global scan ``index`` of ``domain``."""
    return int(rng_for(seed, zlib.crc32(domain.encode()), index).integers(2**63 - 1))
