"""Sparse 3D convolutions in pure PyTorch: gather, GEMM, scatter per kernel offset.

Weights use spconv's layout ``(out, kD, kH, kW, in)`` with no kernel flip, so a
state dict moves unchanged between this backend and :mod:`.spconv_backend`.

The forward and backward passes are an explicit autograd function. Within one
kernel offset no output row (forward) and no input row (backward) is written
twice (see :mod:`.kernel_map`), and offsets are summed in a fixed order, so
results are bitwise reproducible on CPU and do not depend on the order of
atomic adds on GPU either.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn
from torch.autograd.function import once_differentiable

from omnilidar.sparse.kernel_map import (
    KernelMap,
    _triple,
    strided_map,
    submanifold_map,
)
from omnilidar.sparse.tensor import SparseTensor


class _GatherGemmScatter(torch.autograd.Function):
    """``out[o] = sum_k feats[i] @ W[k]`` over the pairs ``(i, o)`` of offset ``k``."""

    # Rows are accumulated with index_add_: indices are unique within an offset, so
    # every row gets one plain add per offset, in offset order (with torch 2.13 on
    # CPU this is 1.5x faster than index_put_(accumulate=True), bitwise the same).

    @staticmethod
    def forward(ctx, feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap) -> torch.Tensor:
        # weight: (K, C_in, C_out)
        out = feats.new_zeros((kmap.num_out, weight.shape[2]))
        for k, i_idx, o_idx in kmap.segments():
            if k == kmap.identity:
                out += feats @ weight[k]
            else:
                out.index_add_(0, o_idx, feats.index_select(0, i_idx) @ weight[k])
        ctx.save_for_backward(feats, weight)
        ctx.kmap = kmap
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        feats, weight = ctx.saved_tensors
        kmap: KernelMap = ctx.kmap
        grad_out = grad_out.contiguous()
        grad_feats = grad_weight = None
        if ctx.needs_input_grad[0]:
            grad_feats = torch.zeros_like(feats)
        if ctx.needs_input_grad[1]:
            grad_weight = torch.zeros_like(weight)
        for k, i_idx, o_idx in kmap.segments():
            if k == kmap.identity:
                g, x = grad_out, feats
            else:
                g, x = grad_out.index_select(0, o_idx), feats.index_select(0, i_idx)
            if grad_feats is not None:
                gx = g @ weight[k].T
                if k == kmap.identity:
                    grad_feats += gx
                else:
                    grad_feats.index_add_(0, i_idx, gx)
            if grad_weight is not None:
                grad_weight[k] = x.T @ g
        return grad_feats, grad_weight, None


def sparse_conv_features(feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap) -> torch.Tensor:
    """Apply a kernel map: ``feats (N_in, C_in)``, spconv-layout ``weight``.

    ``weight`` is ``(C_out, kD, kH, kW, C_in)``; returns ``(N_out, C_out)``.
    """
    c_out, c_in = weight.shape[0], weight.shape[-1]
    # Under autocast (AMP training on CUDA) the products run in the autocast dtype, as a
    # dense layer's would; inside the function autocast is off so every operand agrees.
    device_type = feats.device.type
    dtype = torch.get_autocast_dtype(device_type) if torch.is_autocast_enabled(device_type) else feats.dtype
    w = weight.reshape(c_out, -1, c_in).permute(1, 2, 0).to(dtype)  # (K, C_in, C_out)
    if w.shape[0] != kmap.kernel_volume:
        raise ValueError(f"weight has {w.shape[0]} kernel offsets, kernel map has {kmap.kernel_volume}")
    if feats.shape[0] != kmap.num_in:
        raise ValueError(f"kernel map expects {kmap.num_in} input rows, got {feats.shape[0]}")
    with torch.autocast(device_type, enabled=False):
        return _GatherGemmScatter.apply(feats.to(dtype), w, kmap)


@dataclass
class StridedEntry:
    """What a strided convolution leaves in the cache for its inverse."""

    kmap: KernelMap
    kernel_size: tuple[int, int, int]
    in_coords: torch.Tensor
    in_shape: tuple[int, int, int]
    out_coords: torch.Tensor
    out_shape: tuple[int, int, int]


@dataclass
class SubmEntry:
    kmap: KernelMap
    kernel_size: tuple[int, int, int]
    dilation: tuple[int, int, int]
    coords: torch.Tensor


class _SparseConvBase(nn.Module):
    """Holds a spconv-layout weight ``(out, kD, kH, kW, in)`` and an optional bias."""

    def __init__(self, in_channels, out_channels, kernel_size=3, stride=1, padding=0, dilation=1,
                 bias=False, indice_key=None):
        super().__init__()
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        self.kernel_size = _triple(kernel_size)
        self.stride = _triple(stride)
        self.padding = _triple(padding)
        self.dilation = _triple(dilation)
        self.indice_key = indice_key
        self.weight = nn.Parameter(torch.empty(self.out_channels, *self.kernel_size, self.in_channels))
        self.bias = nn.Parameter(torch.empty(self.out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """Uniform in +-1/sqrt(fan_in) (PyTorch's conv default), from ``generator``."""
        fan_in = self.in_channels * math.prod(self.kernel_size)
        bound = 1.0 / math.sqrt(fan_in)
        with torch.no_grad():
            nn.init.uniform_(self.weight, -bound, bound, generator=generator)
            if self.bias is not None:
                nn.init.uniform_(self.bias, -bound, bound, generator=generator)

    def _finish(self, x: SparseTensor, feats, coords, shape) -> SparseTensor:
        if self.bias is not None:
            feats = feats + self.bias.to(feats.dtype)
        return SparseTensor(feats, coords, shape, x.batch_size, x.cache)

    def _check_input(self, x: SparseTensor) -> None:
        if x.feats.shape[1] != self.in_channels:
            raise ValueError(f"{type(self).__name__} expects {self.in_channels} channels, got {x.feats.shape[1]}")

    def extra_repr(self) -> str:
        s = f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}"
        if self.stride != (1, 1, 1):
            s += f", stride={self.stride}"
        if self.indice_key:
            s += f", indice_key={self.indice_key!r}"
        return s


class SubMConv3d(_SparseConvBase):
    """Submanifold convolution: outputs exactly on the input coordinates."""

    def __init__(self, in_channels, out_channels, kernel_size=3, stride=1, padding=0, dilation=1,
                 bias=False, indice_key=None):
        super().__init__(in_channels, out_channels, kernel_size, 1, padding, dilation, bias, indice_key)

    def kernel_map(self, x: SparseTensor) -> KernelMap | None:
        """The (possibly cached) map; None for a 1x1x1 kernel (a plain matmul)."""
        if self.kernel_size == (1, 1, 1):
            return None
        entry = x.cache.get(self.indice_key) if self.indice_key else None
        if entry is not None:
            if not isinstance(entry, SubmEntry) or entry.kernel_size != self.kernel_size \
                    or entry.dilation != self.dilation or entry.coords is not x.coords:
                raise ValueError(f"indice_key {self.indice_key!r} reused for a different layer geometry")
            return entry.kmap
        kmap = submanifold_map(x.coords, x.spatial_shape, self.kernel_size, self.dilation)
        if self.indice_key:
            x.cache[self.indice_key] = SubmEntry(kmap, self.kernel_size, self.dilation, x.coords)
        return kmap

    def forward(self, x: SparseTensor) -> SparseTensor:
        self._check_input(x)
        kmap = self.kernel_map(x)
        if kmap is None:
            feats = x.feats @ self.weight.reshape(self.out_channels, self.in_channels).T.to(x.feats.dtype)
        else:
            feats = sparse_conv_features(x.feats, self.weight, kmap)
        return self._finish(x, feats, x.coords, x.spatial_shape)


class SparseConv3d(_SparseConvBase):
    """Regular sparse convolution (typically strided): new, coarser coordinates."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        self._check_input(x)
        entry = x.cache.get(self.indice_key) if self.indice_key else None
        if isinstance(entry, StridedEntry) and entry.in_coords is x.coords and entry.kernel_size == self.kernel_size:
            kmap, out_coords, out_shape = entry.kmap, entry.out_coords, entry.out_shape
        else:
            kmap, out_coords, out_shape = strided_map(
                x.coords, x.spatial_shape, self.kernel_size, self.stride, self.padding, self.dilation
            )
            if self.indice_key:
                x.cache[self.indice_key] = StridedEntry(
                    kmap, self.kernel_size, x.coords, x.spatial_shape, out_coords, out_shape
                )
        feats = sparse_conv_features(x.feats, self.weight, kmap)
        return self._finish(x, feats, out_coords, out_shape)


class SparseInverseConv3d(_SparseConvBase):
    """Transposed convolution back onto the input coordinates of the strided
    convolution that shares its ``indice_key`` (spconv's inverse conv)."""

    def __init__(self, in_channels, out_channels, kernel_size, indice_key, bias=False):
        if not indice_key:
            raise ValueError("SparseInverseConv3d needs the indice_key of the convolution it inverts")
        super().__init__(in_channels, out_channels, kernel_size, 1, 0, 1, bias, indice_key)

    def forward(self, x: SparseTensor) -> SparseTensor:
        self._check_input(x)
        entry = x.cache.get(self.indice_key)
        if not isinstance(entry, StridedEntry):
            raise ValueError(f"no strided convolution with indice_key {self.indice_key!r} ran before this inverse")
        if entry.kernel_size != self.kernel_size or entry.out_coords.shape[0] != x.num_voxels:
            raise ValueError(f"inverse convolution {self.indice_key!r} does not match its strided convolution")
        feats = sparse_conv_features(x.feats, self.weight, entry.kmap.transposed())
        return self._finish(x, feats, entry.in_coords, entry.in_shape)
