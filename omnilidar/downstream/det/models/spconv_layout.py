"""Sparse-convolution weights from OpenPCDet checkpoints of any spconv version.

Our sparse convolutions hold spconv 2's implicit-GEMM layout ``(out, k1, k2, k3, in)``.
Checkpoints trained with spconv 1.x store ``(k1, k2, k3, in, out)``; like
OpenPCDet's ``_load_state_dict`` on an implicit-GEMM model, a five-dimensional
weight whose shape differs from ours is read as that layout and permuted.
"""

from __future__ import annotations

import torch


def adapt_spconv_weights(state: dict[str, torch.Tensor], reference: dict[str, torch.Tensor]) -> dict:
    """``state`` with every 5-D weight that does not match ``reference``'s shape but
    does as spconv 1.x ``(k1, k2, k3, in, out)`` permuted to ``(out, k1, k2, k3, in)``."""
    out = dict(state)
    for key, value in state.items():
        target = reference.get(key)
        if target is None or value.ndim != 5 or value.shape == target.shape:
            continue
        permuted = value.permute(4, 0, 1, 2, 3)
        if permuted.shape == target.shape:
            out[key] = permuted.contiguous()
    return out
