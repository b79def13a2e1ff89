"""The OmniLiDAR denoiser: an R2DM-style Efficient UNet over (2, H, W) range images.

Architecture (REFERENCE section 2 and the OmniLiDAR paper):
- input: the noisy image (log-range, intensity) concatenated with 32 Fourier
  features of the true beam angles (fixed, not learned);
- every 3x3 convolution pads azimuth (W) circularly and elevation (H) with zeros,
  so the seam behind the sensor is not a border;
- residual blocks GroupNorm -> SiLU -> conv -> GroupNorm -> h (1 + s) + b (scale
  and shift from the time/text embedding) -> SiLU -> conv (zero-initialised),
  added to the skip path and scaled by 1/sqrt(2);
- time embedding from logSNR (sinusoidal -> MLP), plus the masked mean of the
  prompt tokens when text conditioning is on;
- x2 down/up-sampling in both axes between levels, one skip per level;
- self-attention at the lowest level; cross-attention to the prompt tokens at the
  configured levels (encoder and decoder); CDFM at the configured (deeper) levels;
  DAFS after every decoder level;
- output: epsilon (2, H, W) from a zero-initialised 3x3 conv.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn as nn
import torch.nn.functional as F

from omnilidar.generator.cdfm import CDFM
from omnilidar.generator.dafs import DAFS
from omnilidar.generator.diffusion import take_columns
from omnilidar.generator.schedule import alpha_sigma


@dataclass(frozen=True)
class UNetConfig:
    """Architecture hyper-parameters (the ``generator.model`` config section)."""

    in_channels: int = 2
    coord_channels: int = 32
    base_channels: int = 64
    channel_multipliers: tuple[int, ...] = (1, 2, 4, 8)
    num_res_blocks: int | tuple[int, ...] = 3  # one number for every level, or one per level
    groupnorm_groups: int = 8
    attention_head_dim: int = 32
    dropout: float = 0.0
    text_dim: int = 384
    cross_attention: bool = True
    cross_attention_levels: tuple[int, ...] = (1, 2, 3)
    cdfm: bool = True
    cdfm_levels: tuple[int, ...] = (2, 3)
    cdfm_groups: int = 4
    mamba_d_state: int = 16
    mamba_d_conv: int = 4
    mamba_expand: int = 2
    mamba_backend: str = "auto"
    dafs: bool = True
    dafs_bound: float = 0.5
    dafs_embed_dim: int = 64
    num_domains: int = 8
    logsnr_range: tuple[float, float] = field(default=(-15.0, 15.0))
    epsilon_output: str = "direct"
    # "domain_mean": the network denoises the residual from its domain's mean training image
    # (a buffer filled at training time and saved with the weights); "zero": the plain image.
    prior: str = "zero"

    @property
    def num_levels(self) -> int:
        return len(self.channel_multipliers)

    def blocks_at(self, level: int) -> int:
        """Residual blocks of the encoder and of the decoder at ``level``."""
        blocks = self.num_res_blocks
        return blocks if isinstance(blocks, int) else blocks[level]

    def validate(self) -> None:
        n = self.num_levels
        if not isinstance(self.num_res_blocks, int) and len(self.num_res_blocks) != n:
            raise ValueError(f"num_res_blocks {list(self.num_res_blocks)} has {len(self.num_res_blocks)} entries "
                             f"for {n} UNet levels")
        for name in ("cross_attention_levels", "cdfm_levels"):
            bad = [lv for lv in getattr(self, name) if not 0 <= lv < n]
            if bad:
                raise ValueError(f"{name} {bad} outside the {n} UNet levels 0..{n - 1}")
        widths = [self.base_channels * m for m in self.channel_multipliers]
        if any(w % self.groupnorm_groups for w in widths):
            raise ValueError(f"channel widths {widths} are not divisible by {self.groupnorm_groups} GroupNorm groups")
        if self.epsilon_output not in ("direct", "v_skip"):
            raise ValueError(f"epsilon_output must be 'direct' or 'v_skip', got {self.epsilon_output!r}")
        if self.cdfm and any(widths[lv] % self.cdfm_groups for lv in self.cdfm_levels):
            raise ValueError(f"CDFM groups {self.cdfm_groups} do not divide the widths {widths}")


class CircularConv2d(nn.Conv2d):
    """Conv2d whose padding wraps around azimuth (last axis) and is zero along elevation."""

    def __init__(self, in_ch: int, out_ch: int, kernel_size: int = 3, stride: int = 1):
        super().__init__(in_ch, out_ch, kernel_size, stride=stride, padding=0)
        self.pad = kernel_size // 2

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = self.pad
        if p:
            x = F.pad(x, (p, p, 0, 0), mode="circular")
            x = F.pad(x, (0, 0, p, p))
        return super().forward(x)


def _zero(module: nn.Module) -> nn.Module:
    for p in module.parameters():
        nn.init.zeros_(p)
    return module


def logsnr_embedding(logsnr: torch.Tensor, dim: int, logsnr_range: tuple[float, float]) -> torch.Tensor:
    """Sinusoidal embedding of logSNR mapped to [0, 1000] (the usual timestep scale)."""
    lo, hi = logsnr_range
    s = (logsnr.float().clamp(lo, hi) - lo) / (hi - lo) * 1000.0
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=s.device, dtype=torch.float32) / half)
    ang = s[:, None] * freqs[None]
    return torch.cat([torch.sin(ang), torch.cos(ang)], dim=-1)


class ResBlock(nn.Module):
    def __init__(self, in_ch: int, out_ch: int, emb_dim: int, groups: int, dropout: float):
        super().__init__()
        self.norm1 = nn.GroupNorm(groups, in_ch)
        self.conv1 = CircularConv2d(in_ch, out_ch)
        self.emb = nn.Linear(emb_dim, 2 * out_ch)
        self.norm2 = nn.GroupNorm(groups, out_ch)
        self.dropout = nn.Dropout(dropout)
        self.conv2 = _zero(CircularConv2d(out_ch, out_ch))
        self.skip = nn.Identity() if in_ch == out_ch else nn.Conv2d(in_ch, out_ch, 1)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        scale, shift = self.emb(F.silu(emb))[:, :, None, None].chunk(2, dim=1)
        h = self.norm2(h) * (1.0 + scale) + shift
        h = self.conv2(self.dropout(F.silu(h)))
        return (h + self.skip(x)) * (1.0 / math.sqrt(2.0))


class SelfAttention(nn.Module):
    def __init__(self, ch: int, groups: int, head_dim: int):
        super().__init__()
        self.heads = max(1, ch // head_dim)
        self.norm = nn.GroupNorm(groups, ch)
        self.qkv = nn.Conv2d(ch, 3 * ch, 1)
        self.proj = _zero(nn.Conv2d(ch, ch, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q, k, v = self.qkv(self.norm(x)).reshape(b, 3, self.heads, c // self.heads, h * w).transpose(-1, -2).unbind(1)
        out = F.scaled_dot_product_attention(q, k, v)
        out = out.transpose(-1, -2).reshape(b, c, h, w)
        return x + self.proj(out)


class CrossAttention(nn.Module):
    """Queries from the feature map, keys/values from the prompt tokens (padding masked)."""

    def __init__(self, ch: int, text_dim: int, groups: int, head_dim: int):
        super().__init__()
        self.heads = max(1, ch // head_dim)
        self.norm = nn.GroupNorm(groups, ch)
        self.q = nn.Conv2d(ch, ch, 1)
        self.kv = nn.Linear(text_dim, 2 * ch)
        self.proj = _zero(nn.Conv2d(ch, ch, 1))

    def forward(self, x: torch.Tensor, tokens: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        nh = self.heads
        q = self.q(self.norm(x)).reshape(b, nh, c // nh, h * w).transpose(-1, -2)
        k, v = self.kv(tokens.to(x.dtype)).reshape(b, -1, 2, nh, c // nh).permute(2, 0, 3, 1, 4).unbind(0)
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask[:, None, None, :])
        return x + self.proj(out.transpose(-1, -2).reshape(b, c, h, w))


class Level(nn.Module):
    """Residual blocks then the optional cross-attention, CDFM and DAFS of one UNet level."""

    def __init__(self, in_ch, out_ch, n_blocks, emb_dim, cfg: UNetConfig, level: int, decoder: bool):
        super().__init__()
        g = cfg.groupnorm_groups
        self.blocks = nn.ModuleList(
            [ResBlock(in_ch if i == 0 else out_ch, out_ch, emb_dim, g, cfg.dropout) for i in range(n_blocks)]
        )
        self.cross = (
            CrossAttention(out_ch, cfg.text_dim, g, cfg.attention_head_dim)
            if cfg.cross_attention and level in cfg.cross_attention_levels
            else None
        )
        self.cdfm = (
            CDFM(out_ch, cfg.cdfm_groups, cfg.mamba_d_state, cfg.mamba_d_conv, cfg.mamba_expand, cfg.mamba_backend)
            if cfg.cdfm and level in cfg.cdfm_levels
            else None
        )
        self.dafs = DAFS(out_ch, cfg.num_domains, cfg.dafs_embed_dim, cfg.dafs_bound) if decoder and cfg.dafs else None

    def forward(self, x, emb, tokens, mask, domain):
        for block in self.blocks:
            x = block(x, emb)
        if self.cross is not None:
            x = self.cross(x, tokens, mask)
        if self.cdfm is not None:
            x = self.cdfm(x)
        if self.dafs is not None:
            x = self.dafs(x, domain)
        return x


class Upsample(nn.Module):
    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.conv = CircularConv2d(in_ch, out_ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="nearest"))


class EfficientUNet(nn.Module):
    """Epsilon-predicting denoiser ``f(x_t, logSNR, domain, tokens, mask) -> eps``.

    ``coords`` is the (coord_channels, H, W) beam-angle feature map of the range
    image geometry; it is a non-persistent buffer (rebuilt from the config).
    """

    def __init__(self, cfg: UNetConfig, coords: torch.Tensor):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        if coords.shape[0] != cfg.coord_channels:
            raise ValueError(f"coords have {coords.shape[0]} channels, config says {cfg.coord_channels}")
        down = 2 ** (cfg.num_levels - 1)
        if coords.shape[1] % down or coords.shape[2] % down:
            raise ValueError(f"range image {tuple(coords.shape[1:])} is not divisible by {down} ({cfg.num_levels} levels)")
        self.register_buffer("coords", coords.float().clone(), persistent=False)
        if cfg.prior == "domain_mean":  # filled by set_prior_mean; persistent, so checkpoints carry it
            self.register_buffer("prior_mean", torch.zeros(cfg.num_domains, cfg.in_channels, *coords.shape[1:]))
        widths = [cfg.base_channels * m for m in cfg.channel_multipliers]
        base, emb_dim, g = cfg.base_channels, 4 * cfg.base_channels, cfg.groupnorm_groups
        self.time_mlp = nn.Sequential(nn.Linear(base, emb_dim), nn.SiLU(), nn.Linear(emb_dim, emb_dim))
        self.text_pool = nn.Linear(cfg.text_dim, emb_dim) if cfg.cross_attention else None
        self.stem = CircularConv2d(cfg.in_channels + cfg.coord_channels, widths[0])

        self.down = nn.ModuleList()
        self.enc = nn.ModuleList()
        prev = widths[0]
        for lv, w in enumerate(widths):
            self.down.append(nn.Identity() if lv == 0 else CircularConv2d(prev, w, stride=2))
            self.enc.append(Level(w, w, cfg.blocks_at(lv), emb_dim, cfg, lv, decoder=False))
            prev = w
        top = widths[-1]
        self.mid1 = ResBlock(top, top, emb_dim, g, cfg.dropout)
        self.mid_attn = SelfAttention(top, g, cfg.attention_head_dim)
        self.mid_cross = CrossAttention(top, cfg.text_dim, g, cfg.attention_head_dim) if cfg.cross_attention else None
        self.mid2 = ResBlock(top, top, emb_dim, g, cfg.dropout)

        self.dec = nn.ModuleList()
        self.up = nn.ModuleList()
        for lv in reversed(range(cfg.num_levels)):
            w = widths[lv]
            self.dec.append(Level(2 * w, w, cfg.blocks_at(lv), emb_dim, cfg, lv, decoder=True))
            self.up.append(Upsample(w, widths[lv - 1]) if lv > 0 else nn.Identity())
        self.head_norm = nn.GroupNorm(g, widths[0])
        self.head = _zero(CircularConv2d(widths[0], cfg.in_channels))

    def forward(
        self,
        x: torch.Tensor,
        logsnr: torch.Tensor,
        domain: torch.Tensor,
        tokens: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        columns: torch.Tensor | None = None,
        raw_output: bool = False,
    ) -> torch.Tensor:
        """``columns`` (B, W') selects, per scan, the image columns ``x`` holds (an azimuth
        window in training); None = ``x`` is the full sweep. ``raw_output``: the head's output
        before it becomes epsilon (v of the image for ``v_skip``; the loss of ``loss_weighting:
        v_uniform``)."""
        b = x.shape[0]
        if self.cfg.cross_attention and (tokens is None or mask is None):
            raise ValueError("this denoiser is text-conditioned: pass prompt tokens and mask")
        emb = self.time_mlp(logsnr_embedding(logsnr.expand(b), self.cfg.base_channels, self.cfg.logsnr_range))
        if self.text_pool is not None:
            m = mask.to(tokens.dtype)[..., None]
            pooled = (tokens * m).sum(1) / m.sum(1).clamp_min(1.0)
            emb = emb + self.text_pool(pooled)
        if columns is None:
            coords = self.coords.to(x.dtype).expand(b, -1, -1, -1)
        else:  # (C, H, B, W') -> (B, C, H, W')
            coords = self.coords.to(x.dtype)[:, :, columns].permute(2, 0, 1, 3)
        alpha, sigma = alpha_sigma(logsnr.float().expand(b)[:, None, None, None])
        prior = self._prior(domain, columns, b)
        if prior is not None:  # the network sees x_t of the residual x0 - mean: x_t - alpha mean
            x = (x.float() - alpha * prior).to(x.dtype)
        h = self.stem(torch.cat([x, coords], dim=1))
        skips = []
        for down, level in zip(self.down, self.enc):
            h = level(down(h), emb, tokens, mask, domain)
            skips.append(h)
        h = self.mid1(h, emb)
        h = self.mid_attn(h)
        if self.mid_cross is not None:
            h = self.mid_cross(h, tokens, mask)
        h = self.mid2(h, emb)
        for level, up in zip(self.dec, self.up):
            h = up(level(torch.cat([h, skips.pop()], dim=1), emb, tokens, mask, domain))
        out = self.head(F.silu(self.head_norm(h)))
        if self.cfg.epsilon_output == "direct":
            return out  # epsilon is the same for the image and for its residual
        if raw_output:  # F learns the residual's v; as the image's v = alpha eps - sigma x0:
            return out if prior is None else (out.float() - sigma * prior).to(out.dtype)
        # v_skip: eps = sigma x_t + alpha F. The output is still epsilon (same loss and
        # samplers), but near t = 1 (alpha -> 0) it no longer needs the network to be
        # exact to 1e-4 for x0 = (x_t - sigma eps) / alpha to be usable; F learns v.
        # With a prior x_t is the residual's, so x0 = alpha x_t + sigma^2 mean - sigma F: the
        # untrained network (F = 0) already predicts the domain's mean image at high noise.
        return (sigma * x.float() + alpha * out.float()).to(out.dtype)

    def _prior(self, domain: torch.Tensor, columns: torch.Tensor | None, b: int) -> torch.Tensor | None:
        """(B, C, H, W') mean image of each scan's domain (its window's columns), or None."""
        if self.cfg.prior != "domain_mean":
            return None
        mean = self.prior_mean[domain.expand(b)]
        return mean if columns is None else take_columns(mean, columns)

    def set_prior_mean(self, means: torch.Tensor) -> None:
        """Store each domain's mean training image (num_domains, C, H, W)."""
        if self.cfg.prior != "domain_mean":
            raise ValueError("this denoiser has no prior (generator.diffusion.prior: zero)")
        self.prior_mean.copy_(means.to(self.prior_mean))


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def parameter_breakdown(model: "EfficientUNet") -> dict[str, int]:
    """Trainable parameters by part: the text conditioning (cross-attention and the pooled-prompt
    projection), CDFM, DAFS, and the backbone (everything else); ``total`` is their sum."""

    def of(*modules: nn.Module | None) -> int:
        return sum(count_parameters(m) for m in modules if m is not None)

    parts = {
        "cross_attention": of(model.text_pool, *(m for m in model.modules() if isinstance(m, CrossAttention))),
        "cdfm": of(*(m for m in model.modules() if isinstance(m, CDFM))),
        "dafs": of(*(m for m in model.modules() if isinstance(m, DAFS))),
    }
    total = count_parameters(model)
    return {"backbone": total - sum(parts.values()), **parts, "total": total}


def range_image_spec(settings: dict):
    """The RangeImageSpec of a validated ``generator`` section."""
    from omnilidar.data.range_image import RangeImageSpec

    r = settings["range_image"]
    return RangeImageSpec(r["height"], r["width"], r["fov_up_deg"], r["fov_down_deg"], r["min_range"], r["max_range"])


def unet_config(settings: dict, text_dim: int, num_domains: int) -> UNetConfig:
    """UNetConfig from a validated ``generator`` section plus the data-dependent sizes."""
    m, d = settings["model"], settings["diffusion"]
    return UNetConfig(
        base_channels=m["base_channels"],
        channel_multipliers=tuple(m["channel_multipliers"]),
        num_res_blocks=m["num_res_blocks"] if isinstance(m["num_res_blocks"], int) else tuple(m["num_res_blocks"]),
        groupnorm_groups=m["groupnorm_groups"],
        attention_head_dim=m["attention_head_dim"],
        dropout=m["dropout"],
        text_dim=int(text_dim),
        cross_attention=m["cross_attention"],
        cross_attention_levels=tuple(m["cross_attention_levels"]),
        cdfm=m["cdfm"],
        cdfm_levels=tuple(m["cdfm_levels"]),
        cdfm_groups=m["cdfm_groups"],
        mamba_d_state=m["mamba"]["d_state"],
        mamba_d_conv=m["mamba"]["d_conv"],
        mamba_expand=m["mamba"]["expand"],
        mamba_backend=m["mamba"]["backend"],
        dafs=m["dafs"],
        dafs_bound=m["dafs_bound"],
        dafs_embed_dim=m["dafs_embed_dim"],
        num_domains=int(num_domains),
        logsnr_range=(float(d["logsnr_min"]), float(d["logsnr_max"])),
        epsilon_output=d["epsilon_output"],
        prior=d.get("prior", "zero"),
    )


def build_denoiser(settings: dict, text_dim: int, num_domains: int) -> EfficientUNet:
    """The denoiser for a validated ``generator`` section (beam-angle features from its geometry).

    Raises InputError (naming the config key) for inconsistent architecture settings.
    """
    from omnilidar.data.range_image import beam_angle_features
    from omnilidar.errors import InputError

    spec = range_image_spec(settings)
    try:
        cfg = unet_config(settings, text_dim, num_domains)
        return EfficientUNet(cfg, torch.from_numpy(beam_angle_features(spec)))
    except ValueError as err:
        raise InputError(None, f"generator.model: {err}") from None
