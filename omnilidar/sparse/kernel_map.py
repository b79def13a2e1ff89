"""Kernel maps: which input voxel feeds which output voxel through which weight.

A kernel map lists, for every kernel offset ``k`` (flattened in the weight's
``kD, kH, kW`` order), the pairs ``(in_idx, out_idx)`` with
``out[out_idx] += feats[in_idx] @ W[k]``. For every convolution type here a
given output receives at most one input per offset and a given input feeds at
most one output per offset, so within one offset both index lists are free of
duplicates. That is what makes the gather-GEMM-scatter of :mod:`.conv`
deterministic: no two writes of one offset ever hit the same row.

Coordinates are packed into int64 keys (:func:`.tensor.pack_coords`) and looked
up in a sorted key table with a vectorised binary search
(:class:`KeyTable`): deterministic, allocation-light, and the same on CPU and
GPU.

Geometry follows ``torch.nn.functional.conv3d`` (cross-correlation, no kernel
flip, the spconv convention):

- submanifold: ``out[i] = sum_k W[k] x[i + (k - centre) * dilation]``,
  outputs on the input coordinates;
- strided: ``out[o] = sum_k W[k] x[o * stride - padding + k * dilation]``,
  outputs on every grid cell of ``[0, out_shape)`` that some input reaches;
- inverse (transposed): the strided map with inputs and outputs swapped,
  outputs back on the strided conv's input coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import product

import torch

from omnilidar.sparse.tensor import pack_coords, unpack_keys


def _triple(value) -> tuple[int, int, int]:
    if isinstance(value, int):
        return (value, value, value)
    value = tuple(int(v) for v in value)
    if len(value) != 3:
        raise ValueError(f"expected an int or 3 ints, got {value}")
    return value


def kernel_offsets(kernel_size, device=None) -> torch.Tensor:
    """``(K, 3)`` int64 kernel positions in weight order (kD major, kW minor)."""
    ks = _triple(kernel_size)
    grid = list(product(range(ks[0]), range(ks[1]), range(ks[2])))
    return torch.tensor(grid, dtype=torch.int64, device=device).reshape(-1, 3)


class KeyTable:
    """Lookup of packed int64 coordinate keys -> row index (or -1 if absent)."""

    def __init__(self, keys: torch.Tensor):
        self.sorted_keys, self.order = torch.sort(keys)

    def find(self, queries: torch.Tensor) -> torch.Tensor:
        if self.sorted_keys.numel() == 0:
            return torch.full_like(queries, -1)
        pos = torch.searchsorted(self.sorted_keys, queries)
        pos = pos.clamp_(max=self.sorted_keys.numel() - 1)
        hit = self.sorted_keys[pos] == queries
        return torch.where(hit, self.order[pos], torch.full_like(pos, -1))


@dataclass(frozen=True)
class KernelMap:
    """Pairs of one sparse convolution, grouped by kernel offset.

    in_idx, out_idx: int64 ``(P,)``; offset ``k`` owns ``bounds[k]:bounds[k+1]``.
    identity: the offset whose pairs are exactly ``i -> i`` for every row (the
        submanifold centre), which the convolution applies without gathering.
    """

    in_idx: torch.Tensor
    out_idx: torch.Tensor
    bounds: tuple[int, ...]
    num_in: int
    num_out: int
    identity: int | None = None

    @property
    def kernel_volume(self) -> int:
        return len(self.bounds) - 1

    def segments(self):
        """Yield ``(k, in_idx_k, out_idx_k)`` for every offset with pairs."""
        for k in range(self.kernel_volume):
            a, b = self.bounds[k], self.bounds[k + 1]
            if b > a:
                yield k, self.in_idx[a:b], self.out_idx[a:b]

    def transposed(self) -> "KernelMap":
        """The map of the inverse convolution (outputs become inputs)."""
        return KernelMap(self.out_idx, self.in_idx, self.bounds, self.num_out, self.num_in, self.identity)


def _bounds(counts: torch.Tensor) -> tuple[int, ...]:
    return tuple([0] + torch.cumsum(counts, 0).tolist())


def submanifold_map(coords: torch.Tensor, spatial_shape, kernel_size=3, dilation=1) -> KernelMap:
    """Kernel map of a submanifold convolution (outputs = input coordinates).

    The kernel size must be odd on every axis so that it has a centre.
    """
    ks, dil = _triple(kernel_size), _triple(dilation)
    if any(k % 2 == 0 for k in ks):
        raise ValueError(f"submanifold convolution needs an odd kernel size, got {ks}")
    n = coords.shape[0]
    device = coords.device
    sx, sy, sz = (int(s) for s in spatial_shape)
    offs = ((kernel_offsets(ks) - torch.tensor([k // 2 for k in ks])) * torch.tensor(dil)).tolist()  # weight order
    c = coords.long()
    # Keys are linear in the coordinates, so a neighbour's key is the row's key plus the
    # offset's key delta. Searching the rows in key order keeps every query batch sorted
    # (cache-friendly binary search); results go back to the rows' own order.
    table = KeyTable(pack_coords(c, spatial_shape))
    sorted_keys, by_key = table.sorted_keys, table.order
    sorted_c = c[by_key]
    last = max(n - 1, 0)
    # Offsets k and K-1-k are opposite, so i -> j under one is j -> i under the other:
    # only the first half is searched; the centre maps every row to itself.
    half = len(offs) // 2
    found = torch.full((half, n), -1, dtype=torch.int64, device=device)
    # Offsets that differ only on the minor axis look in one run of keys: one binary search
    # for the lowest, then the next few sorted keys hold the others if they exist.
    columns: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for k, (o0, o1, o2) in enumerate(offs[:half]):
        columns.setdefault((o0, o1), []).append((k, o2))
    for (o0, o1), members in columns.items():
        low = sorted_keys + ((o0 * sy + o1) * sz + members[0][1])
        start = torch.searchsorted(sorted_keys, low)
        span = members[-1][1] - members[0][1]
        candidates = [(start + j).clamp_(max=last) for j in range(span + 1)]
        gaps = [sorted_keys[pos] - low for pos in candidates]
        for k, o2 in members:
            target = o2 - members[0][1]
            at = torch.full_like(start, -1)
            for pos, gap in zip(candidates[:target + 1], gaps[:target + 1]):
                at = torch.where(gap == target, pos, at)
            hit = at >= 0
            for axis, (o, size) in enumerate(zip((o0, o1, o2), (sx, sy, sz))):
                if o:  # a key can wrap into a neighbouring row of the grid: check the axis itself
                    moved = sorted_c[:, axis + 1] + o
                    hit &= (moved >= 0) & (moved < size)
            found[k, by_key] = torch.where(hit, by_key[at.clamp(min=0)], -1)
    rows = torch.arange(n, device=device)
    ins, outs = [], []
    for k in range(half):
        valid = found[k] >= 0
        ins.append(found[k][valid])
        outs.append(rows[valid])
    mirrored = []
    for k in reversed(range(half)):  # offset K-1-k: pairs swapped, listed by output row
        order = torch.argsort(ins[k])
        mirrored.append((outs[k][order], ins[k][order]))
    ins += [rows] + [m[0] for m in mirrored]
    outs += [rows] + [m[1] for m in mirrored]
    counts = torch.tensor([len(i) for i in ins], dtype=torch.int64)
    return KernelMap(torch.cat(ins), torch.cat(outs), _bounds(counts), n, n, half)


def strided_output_shape(spatial_shape, kernel_size, stride, padding, dilation) -> tuple[int, int, int]:
    """Output grid size, as for ``conv3d``."""
    ks, st, pd, dl = (_triple(v) for v in (kernel_size, stride, padding, dilation))
    out = tuple((s + 2 * p - d * (k - 1) - 1) // t + 1 for s, k, t, p, d in zip(spatial_shape, ks, st, pd, dl))
    if min(out) < 1:
        raise ValueError(f"spatial_shape {tuple(spatial_shape)} too small for kernel {ks}, stride {st}")
    return out


def strided_map(
    coords: torch.Tensor, spatial_shape, kernel_size=2, stride=2, padding=0, dilation=1
) -> tuple[KernelMap, torch.Tensor, tuple[int, int, int]]:
    """Kernel map of a regular (strided) sparse convolution.

    Returns the map, the output coordinates (int32, sorted batch-major) and the
    output grid size. Every output cell reached by some input is active.
    """
    ks, st, pd, dl = (_triple(v) for v in (kernel_size, stride, padding, dilation))
    out_shape = strided_output_shape(spatial_shape, ks, st, pd, dl)
    n = coords.shape[0]
    device = coords.device
    c = coords.long()
    # Per axis and kernel index k: input coordinate x reaches output (x + p - k * d) / s
    # when that divides and lands in the grid; an offset's pairs are where all three do.
    outs, hits = [], []
    for axis in range(3):
        num = c[None, :, axis + 1] + pd[axis] - (torch.arange(ks[axis], device=device) * dl[axis])[:, None]
        o = torch.div(num, st[axis], rounding_mode="floor")  # (k_axis, N)
        outs.append(o)
        hits.append((o * st[axis] == num) & (o >= 0) & (o < out_shape[axis]))
    valid = (hits[0][:, None, None] & hits[1][None, :, None] & hits[2][None, None, :]).reshape(math.prod(ks), n)
    k, in_idx = torch.nonzero(valid, as_tuple=True)  # offset-major, inputs ascending within one
    kz, ky, kx = k // (ks[1] * ks[2]), k // ks[2] % ks[1], k % ks[2]
    out_keys = ((c[in_idx, 0] * out_shape[0] + outs[0][kz, in_idx]) * out_shape[1]
                + outs[1][ky, in_idx]) * out_shape[2] + outs[2][kx, in_idx]  # pack_coords' keys
    uniq, out_idx = torch.unique(out_keys, sorted=True, return_inverse=True)
    out_coords = unpack_keys(uniq, out_shape)
    kmap = KernelMap(in_idx, out_idx.reshape(-1), _bounds(valid.sum(1)), n, int(uniq.numel()))
    return kmap, out_coords, out_shape
