"""Domain-Adaptive Feature Scaling (DAFS): bounded per-domain affine modulation.

A learned embedding per domain is mapped to per-channel (gamma, beta), both
bounded by ``lambda * tanh(.)``; features are modulated as
``F' = (1 + gamma) F + beta``. With ``bound < 1`` the scale ``1 + gamma`` stays
strictly positive, so DAFS can re-weight channels per domain but never flip or
zero them. The output layer starts at zero: an untrained DAFS is the identity.
Used in the decoder only.
"""

from __future__ import annotations

import torch
import torch.nn as nn


class DAFS(nn.Module):
    """Per-domain bounded scale/shift of a (B, C, H, W) feature map."""

    def __init__(self, channels: int, num_domains: int, embed_dim: int = 64, bound: float = 0.5):
        super().__init__()
        if num_domains < 1:
            raise ValueError("DAFS needs at least one domain")
        if not 0.0 < bound:
            raise ValueError(f"DAFS bound must be positive, got {bound}")
        self.bound = float(bound)
        self.embed = nn.Embedding(num_domains, embed_dim)
        self.to_affine = nn.Sequential(nn.SiLU(), nn.Linear(embed_dim, 2 * channels))
        nn.init.zeros_(self.to_affine[-1].weight)
        nn.init.zeros_(self.to_affine[-1].bias)

    def affine(self, domain: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(gamma, beta), each (B, C), with |gamma|, |beta| <= bound."""
        gamma, beta = self.to_affine(self.embed(domain)).chunk(2, dim=-1)
        return self.bound * torch.tanh(gamma), self.bound * torch.tanh(beta)

    def forward(self, feat: torch.Tensor, domain: torch.Tensor) -> torch.Tensor:
        gamma, beta = self.affine(domain)
        return feat * (1.0 + gamma[:, :, None, None].to(feat.dtype)) + beta[:, :, None, None].to(feat.dtype)
