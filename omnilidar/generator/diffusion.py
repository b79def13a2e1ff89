"""Diffusion on range images: the training objective and the reverse (sampling) loop.

Continuous time t in [0, 1] with a cosine log-SNR schedule
(:mod:`omnilidar.generator.schedule`); the denoiser predicts epsilon. Training noises
a clean batch at t ~ U(0, 1) and weights the epsilon error per scan by min-SNR-gamma;
sampling runs a diffusers-style scheduler (:mod:`omnilidar.generator.samplers`) from
per-scan seeded noise. The mmengine trainer and the sharded sampler are thin
adapters around these two functions.
"""

from __future__ import annotations

import math
import zlib

import torch

from omnilidar.generator.data import rng_for
from omnilidar.generator.samplers import make_scheduler
from omnilidar.generator.schedule import CosineLogSNRSchedule, alpha_sigma, bf16_safe, min_snr_weight


def noised(image: torch.Tensor, t: torch.Tensor, eps: torch.Tensor, schedule: CosineLogSNRSchedule):
    """x_t = alpha(t) x_0 + sigma(t) eps, and the log-SNR at t."""
    logsnr = schedule.logsnr(t)
    alpha, sigma = alpha_sigma(logsnr)
    return alpha[:, None, None, None] * image.float() + sigma[:, None, None, None] * eps, logsnr


def azimuth_windows(width: int, crop_width: int, batch: int, generator: torch.Generator,
                    device: torch.device | str = "cpu") -> torch.Tensor:
    """(batch, crop_width) column indices of one window per scan: ``crop_width``
    consecutive columns from a random start, wrapping around (a sweep is periodic in
    azimuth, so every window is a real piece of a scan)."""
    start = torch.randint(width, (batch,), generator=generator, device=device)
    return (start[:, None] + torch.arange(crop_width, device=device)[None, :]) % width


def take_columns(images: torch.Tensor, columns: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W') the ``columns`` (B, W') of each of ``images`` (B, C, H, W): one window per scan."""
    return torch.gather(images, 3, columns[:, None, None, :].expand(-1, images.shape[1], images.shape[2], -1))


def epsilon_loss(denoiser: torch.nn.Module, image: torch.Tensor, domain: torch.Tensor, tokens: torch.Tensor,
                 mask: torch.Tensor, schedule: CosineLogSNRSchedule, gamma: float,
                 generator: torch.Generator, crop_width: int | None = None,
                 weighting: str = "min_snr", columns: torch.Tensor | None = None) -> torch.Tensor:
    """The denoising loss of one batch at t ~ U(0, 1); t and epsilon come from ``generator``.

    ``weighting``: ``min_snr`` = the min-SNR-gamma weighted epsilon MSE; ``v_uniform`` = the
    unweighted MSE of a v_skip network's own output against v = alpha eps - sigma x0, in fp32.
    In x0 terms min-SNR weighs an error at noise level SNR by min(SNR, gamma), next to nothing
    at high noise, where samplers decide a scan's layout; v_uniform weighs it by SNR + 1, at
    least 1.

    With ``crop_width`` each scan is trained on one azimuth window of that many columns
    (start drawn from ``generator`` first); the denoiser sees the window's true beam
    angles, so the same weights sample full sweeps. ``columns``: the batch is already such windows,
    of these columns (no crop drawn).
    """
    b = image.shape[0]
    if columns is None and crop_width is not None and crop_width < image.shape[-1]:
        columns = azimuth_windows(image.shape[-1], crop_width, b, generator, image.device)
        image = take_columns(image, columns)
    t = torch.rand(b, generator=generator, device=image.device, dtype=torch.float32)
    eps = torch.randn(image.shape, generator=generator, device=image.device, dtype=torch.float32)
    x_t, logsnr = noised(image, t, eps, schedule)
    raw = weighting == "v_uniform"
    extra = ({} if columns is None else {"columns": columns}) | ({"raw_output": True} if raw else {})
    pred = denoiser(x_t, logsnr, domain, tokens, mask, **extra)
    if raw:
        alpha, sigma = alpha_sigma(logsnr)
        v = alpha[:, None, None, None] * eps - sigma[:, None, None, None] * image.float()
        return (pred.float() - v).square().mean()
    per_scan = (pred.float() - eps).square().mean(dim=(1, 2, 3))
    return (min_snr_weight(logsnr, gamma) * per_scan).mean()


def sector_columns(width: int, sectors: int) -> list[slice]:
    """The column blocks of ``sectors`` equal azimuth sectors of an image ``width`` columns wide."""
    step = width // sectors
    if step * sectors != width:
        raise ValueError(f"{sectors} azimuth sectors do not split an image {width} columns wide")
    return [slice(s * step, (s + 1) * step) for s in range(sectors)]


def by_sector(apply, images: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """``apply(images, table[s])`` on each of S = len(table) equal azimuth sectors (column blocks) of
    the (B, C, H, W) images, put back together: a calibration fitted per sector."""
    return torch.cat([apply(images[..., cols], part)
                      for cols, part in zip(sector_columns(images.shape[-1], table.shape[0]), table)], dim=-1)


def apply_return_thresholds(images: torch.Tensor, thresholds: torch.Tensor) -> torch.Tensor:
    """(B, 2, H, W) images with every pixel whose encoded range is at or below its row's threshold
    (H,) made empty (-1 in both channels): a calibrated student's return decision
    (:mod:`omnilidar.generator.return_decision`). Thresholds (S, H) decide each of S equal azimuth
    sectors with its own rows' thresholds."""
    if thresholds.dim() == 2:
        return by_sector(apply_return_thresholds, images, thresholds)
    empty = images[:, 0] <= thresholds.to(images)[None, :, None]
    return torch.where(empty[:, None], torch.full_like(images, -1.0), images)


def apply_range_map(images: torch.Tensor, knots: torch.Tensor) -> torch.Tensor:
    """(B, 2, H, W) images whose encoded ranges at or above their row's lowest student knot move
    along the row's monotone piecewise-linear map from the student's knots ``knots[:, 0]`` to the
    teacher's ``knots[:, 1]`` ((H, 2, K)): a calibrated student's returns
    (:mod:`omnilidar.generator.return_decision`); drop-outs and intensities are untouched. Knots
    (S, H, 2, K) map each of S equal azimuth sectors with its own rows' maps."""
    if knots.dim() == 4:
        return by_sector(apply_range_map, images, knots)
    b, _, h, w = images.shape
    xp, fp = knots[:, 0].to(images), knots[:, 1].to(images)
    x = images[:, 0].permute(1, 0, 2).reshape(h, b * w).contiguous()  # one row of values per image row
    hi = torch.searchsorted(xp.contiguous(), x, right=True).clamp(1, xp.shape[1] - 1)
    x0, x1, y0, y1 = (t.gather(1, i) for t, i in ((xp, hi - 1), (xp, hi), (fp, hi - 1), (fp, hi)))
    frac = torch.where(x1 > x0, (x - x0) / (x1 - x0).clamp_min(1e-12), torch.ones_like(x)).clamp(0.0, 1.0)
    moved = (x >= xp[:, :1]) & (xp != fp).any(dim=1, keepdim=True)  # an identity row keeps its values exactly
    mapped = torch.where(moved, y0 + frac * (y1 - y0), x)
    out = images.clone()
    out[:, 0] = mapped.reshape(h, b, w).permute(1, 0, 2)
    return out


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
    init: torch.Tensor | None = None,
    strength: float = 1.0,
) -> torch.Tensor:
    """Sample one batch: len(seeds) range images (B, 2, H, W) in [-1, 1], float32 on CPU.

    ``tokens`` (T, D) and ``mask`` (T,) are the domain's (first) prompt.

    With ``strength`` < 1 (SDEdit, Meng et al. 2022) the batch starts from ``init`` (B, 2, H, W),
    real scans noised to t = ``strength`` with each scan's seeded noise, and the sampler runs
    ceil(steps * strength) steps from there to 0: the same step density as a full run. Near 0 a
    scan stays its source; at 1 it is a fresh sample (``init`` is then not used).

    A distilled student with calibrated ``return_thresholds`` (attached by
    :func:`~omnilidar.generator.checkpoint.load_generator`) decides its drop-outs with them, and
    with a ``range_map`` maps its returns' ranges (:mod:`omnilidar.generator.return_decision`).
    """
    if not 0.0 < strength <= 1.0:
        raise ValueError(f"strength must be in (0, 1], got {strength}")
    if strength < 1.0 and (init is None or init.shape != (len(seeds), 2, *shape)):
        raise ValueError(f"strength {strength} needs init images of shape {(len(seeds), 2, *shape)}")
    device = next(denoiser.parameters()).device
    kwargs = {"eta": ddim_eta} if sampler == "ddim" else {}
    sched = make_scheduler(sampler, schedule or CosineLogSNRSchedule(), **kwargs)
    sched.set_timesteps(math.ceil(steps * strength - 1e-9), start=strength)
    gens = []
    for s in seeds:
        g = torch.Generator(device=device)
        g.manual_seed(s)
        gens.append(g)
    b = len(seeds)
    x = torch.stack([torch.randn((2, *shape), generator=g, device=device) for g in gens])
    if strength < 1.0:
        alpha, sigma = alpha_sigma(sched.logsnr_at(sched.timesteps[0]))
        x = alpha.to(device) * init.to(device).float() + sigma.to(device) * x
    dom = torch.full((b,), int(domain_index), dtype=torch.long, device=device)
    tok = tokens.to(device).float().expand(b, -1, -1)
    msk = mask.to(device).bool().expand(b, -1)
    for t in sched.timesteps:
        logsnr = sched.logsnr_at(t).to(device).expand(b)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast_bf16 and bf16_safe(logsnr)):
            eps = denoiser(x, logsnr, dom, tok, msk)
        eps = torch.nan_to_num(eps.float(), nan=0.0, posinf=0.0, neginf=0.0)
        x = sched.step(eps, t, x, generator=gens).prev_sample
    x = x.clamp(-1.0, 1.0).float()
    thresholds = getattr(denoiser, "return_thresholds", None)  # a calibrated student's return decision
    if thresholds is not None:
        x = apply_return_thresholds(x, thresholds[int(domain_index)])
    range_map = getattr(denoiser, "range_map", None)  # and its returns' ranges
    if range_map is not None:
        x = apply_range_map(x, range_map[int(domain_index)])
    return x.cpu()


def scan_seed(seed: int, domain: str, index: int) -> int:
    """The per-scan seed of global scan ``index`` of ``domain``."""
    return int(rng_for(seed, zlib.crc32(domain.encode()), index).integers(2**63 - 1))
