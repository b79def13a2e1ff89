"""Choosing a sparse-convolution backend: ``"torch"``, ``"spconv"`` or ``"auto"``.

Both backends expose the same three layer classes with the same parameters, so
a model built with one loads the other's checkpoint unchanged.

``"auto"`` picks spconv on CUDA when it is installed and passes its self-check,
and :data:`CPU_DEFAULT` on CPU. The CPU default comes from
``benchmarks/bench_sparse.py``: on this project's reference CPU the spconv
2.3.8 wheel fails its self-check (wrong submanifold kernel maps), so the
pure-PyTorch backend is the CPU default; it is also the only one that supports
float64 and autograd checks on CPU.
"""

from __future__ import annotations

from types import SimpleNamespace

import torch

from omnilidar.errors import InputError

BACKENDS = ("torch", "spconv", "auto")
CPU_DEFAULT = "torch"


def resolve_backend(name: str = "auto", device: str | torch.device = "cpu") -> str:
    """Turn a configured backend name into ``"torch"`` or ``"spconv"``.

    Raises InputError for an unknown name, and for ``"spconv"`` when spconv is
    missing or fails its self-check on ``device``.
    """
    if name not in BACKENDS:
        raise InputError(None, f"sparse backend must be one of {', '.join(BACKENDS)}; got {name!r}")
    device = torch.device(device)
    if name == "torch":
        return "torch"
    from omnilidar.sparse import spconv_backend

    if name == "spconv":
        problem = spconv_backend.self_check(device)
        if problem is not None:
            raise InputError(None, f"sparse backend 'spconv' is not usable on {device.type}: {problem}")
        return "spconv"
    if device.type == "cuda":
        return "spconv" if spconv_backend.spconv_available(device) else "torch"
    if CPU_DEFAULT == "spconv" and spconv_backend.spconv_available(device):
        return "spconv"
    return "torch"


def conv_layers(name: str = "auto", device: str | torch.device = "cpu") -> SimpleNamespace:
    """The layer classes ``SubMConv3d``, ``SparseConv3d``, ``SparseInverseConv3d``
    of the resolved backend (plus ``name``, the resolved backend name)."""
    resolved = resolve_backend(name, device)
    if resolved == "spconv":
        from omnilidar.sparse import spconv_backend as module
    else:
        from omnilidar.sparse import conv as module
    return SimpleNamespace(
        name=resolved,
        SubMConv3d=module.SubMConv3d,
        SparseConv3d=module.SparseConv3d,
        SparseInverseConv3d=module.SparseInverseConv3d,
    )
