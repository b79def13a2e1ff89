"""Mamba backends and the Cross-Directional Feature Mixing (CDFM) module.

Backends. ``mamba_ssm.Mamba`` (fused CUDA kernels) is used when it is installed
and CUDA is available; otherwise ``mambapy.mamba.MambaBlock`` (pure PyTorch,
parallel scan) runs everywhere. Both hold the same parameters under the same
names and shapes (:func:`mamba_parameter_shapes`), so a checkpoint trained with
one loads strictly into the other.

CDFM. A feature map S (B, C, H, W) is flattened twice: azimuth-major (row by
row, W varies fastest: the scan follows the sensor's sweep) and elevation-major
(column by column, H fastest: it follows one firing's beams). Each flattening is
layer-normalised, split into G channel groups that all go through the *same*
Mamba (groups are folded into the batch), concatenated back and projected by a
linear channel mixer; the two directions are averaged and added to S:

    CDFM(S) = S + 0.5 * (P(M(LN(S_az))) + P(M(LN(S_el))))

The projection P starts at zero so that an untrained CDFM is the identity.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn


def mamba_ssm_available() -> bool:
    """True when the mamba-ssm CUDA package can be imported and CUDA is usable."""
    if not torch.cuda.is_available():
        return False
    try:
        import mamba_ssm  # noqa: F401
    except Exception:  # ImportError, or a broken CUDA extension
        return False
    return True


def resolve_backend(backend: str) -> str:
    """Map ``auto`` to ``mamba_ssm`` (CUDA + installed) or ``mambapy``; validate names."""
    if backend == "auto":
        return "mamba_ssm" if mamba_ssm_available() else "mambapy"
    if backend not in ("mamba_ssm", "mambapy"):
        raise ValueError(f"unknown Mamba backend {backend!r} (auto, mamba_ssm, mambapy)")
    if backend == "mamba_ssm" and not mamba_ssm_available():
        raise ValueError("Mamba backend mamba_ssm requested but mamba-ssm or CUDA is not available")
    return backend


def make_mamba(d_model: int, d_state: int = 16, d_conv: int = 4, expand: int = 2, backend: str = "auto") -> nn.Module:
    """One Mamba mixer (B, L, d_model) -> (B, L, d_model) from the chosen backend."""
    backend = resolve_backend(backend)
    if backend == "mamba_ssm":
        from mamba_ssm import Mamba

        return Mamba(d_model=d_model, d_state=d_state, d_conv=d_conv, expand=expand)
    from mambapy.mamba import MambaBlock, MambaConfig

    cfg = MambaConfig(d_model=d_model, n_layers=1, d_state=d_state, d_conv=d_conv, expand_factor=expand, pscan=True)
    return MambaBlock(cfg)


def mamba_parameter_shapes(d_model: int, d_state: int = 16, d_conv: int = 4, expand: int = 2) -> dict[str, tuple]:
    """Parameter names and shapes of ``mamba_ssm.Mamba`` (mamba_simple.py) with defaults
    ``bias=False``, ``conv_bias=True``, ``dt_rank='auto'`` (= ceil(d_model / 16))."""
    d_inner = expand * d_model
    dt_rank = math.ceil(d_model / 16)
    return {
        "A_log": (d_inner, d_state),
        "D": (d_inner,),
        "in_proj.weight": (2 * d_inner, d_model),
        "conv1d.weight": (d_inner, 1, d_conv),
        "conv1d.bias": (d_inner,),
        "x_proj.weight": (dt_rank + 2 * d_state, d_inner),
        "dt_proj.weight": (d_inner, dt_rank),
        "dt_proj.bias": (d_inner,),
        "out_proj.weight": (d_model, d_inner),
    }


class CDFM(nn.Module):
    """Cross-directional feature mixing with one shared Mamba over G channel groups."""

    def __init__(
        self,
        channels: int,
        groups: int = 4,
        d_state: int = 16,
        d_conv: int = 4,
        expand: int = 2,
        backend: str = "auto",
    ):
        super().__init__()
        if channels % groups:
            raise ValueError(f"CDFM: {channels} channels do not split into {groups} groups")
        self.channels, self.groups = channels, groups
        self.norm = nn.LayerNorm(channels)
        self.mamba = make_mamba(channels // groups, d_state, d_conv, expand, backend)
        self.proj = nn.Linear(channels, channels)
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)

    def _mix(self, seq: torch.Tensor) -> torch.Tensor:
        # seq: (N, L, C) -> groups folded into the batch -> one shared Mamba -> (N, L, C)
        n, length, c = seq.shape
        g = self.groups
        x = self.norm(seq).reshape(n, length, g, c // g).permute(0, 2, 1, 3).reshape(n * g, length, c // g)
        y = self.mamba(x.contiguous())
        y = y.reshape(n, g, length, c // g).permute(0, 2, 1, 3).reshape(n, length, c)
        return self.proj(y)

    def forward(self, s: torch.Tensor) -> torch.Tensor:
        b, c, h, w = s.shape
        az = s.permute(0, 2, 3, 1).reshape(b, h * w, c)  # azimuth-major: W fastest
        el = s.permute(0, 3, 2, 1).reshape(b, w * h, c)  # elevation-major: H fastest
        # The Mamba is shared, so both flattenings (same length) run as one batch.
        mixed = self._mix(torch.cat([az, el], dim=0))
        m_az = mixed[:b].reshape(b, h, w, c).permute(0, 3, 1, 2)
        m_el = mixed[b:].reshape(b, w, h, c).permute(0, 3, 2, 1)
        return s + 0.5 * (m_az + m_el)
