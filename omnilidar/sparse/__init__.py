"""Sparse 3D convolution: a pure-PyTorch backend and an optional spconv backend.

Layers take and return :class:`SparseTensor`; weights use spconv's layout
``(out, kD, kH, kW, in)`` in both backends. Pick a backend with
:func:`conv_layers` (``"torch"``, ``"spconv"`` or ``"auto"``).
"""

from omnilidar.sparse.backend import BACKENDS, conv_layers, resolve_backend
from omnilidar.sparse.conv import SparseConv3d, SparseInverseConv3d, SubMConv3d
from omnilidar.sparse.tensor import SparseTensor

__all__ = [
    "BACKENDS",
    "SparseConv3d",
    "SparseInverseConv3d",
    "SparseTensor",
    "SubMConv3d",
    "conv_layers",
    "resolve_backend",
]
