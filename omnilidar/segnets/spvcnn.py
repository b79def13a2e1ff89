"""SPVCNN: MinkUNet's voxel trunk plus a full-resolution point branch.

Point features are read from the voxel trunk by trilinear devoxelisation at
strides 1 (after the stem), 16 (encoder bottom), 4 (after two up stages) and 1
(decoder top). Between reads, point MLPs (Linear-BN-ReLU: stem -> enc[-1],
enc[-1] -> dec[1], dec[1] -> dec[3]; 32->256, 256->128, 128->96 for W32) carry
the previous point features forward and are added to the fresh reads. Point
features go back to voxels by averaging the points of each voxel, with dropout
0.3 before the two later up stages. The classifier runs on points.

Trilinear weights use voxel centres: at stride ``s`` a point at ``p`` (stride-1
voxel units) sits between the 8 voxels around ``p / s - 0.5``; absent
neighbours get weight 0 and the rest are renormalised (the point's own voxel is
always present, so the sum is never 0).
"""

from __future__ import annotations

import warnings

import torch
from torch import nn
from torch.autograd.function import once_differentiable

from omnilidar.segnets.minkunet import NUM_SEG_CLASSES, UNetTrunk, concat, init_weights, network_input
from omnilidar.segnets.voxelize import SegBatch
from omnilidar.sparse.conv import StridedEntry, SubmEntry
from omnilidar.sparse.kernel_map import KeyTable
from omnilidar.sparse.tensor import SparseTensor, pack_coords

_CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.int64)


def _lookup(x: SparseTensor, batch_idx: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """Row of ``x`` at each (batch, cell) or -1; cells may lie outside the grid."""
    shape = torch.tensor(x.spatial_shape, device=cells.device)
    inside = ((cells >= 0) & (cells < shape)).all(-1)
    safe = torch.where(inside[..., None], cells, torch.zeros_like(cells))
    rows = torch.cat([batch_idx[..., None], safe], -1).reshape(-1, 4)
    found = KeyTable(pack_coords(x.coords, x.spatial_shape)).find(pack_coords(rows, x.spatial_shape))
    found = found.reshape(cells.shape[:-1])
    return torch.where(inside, found, torch.full_like(found, -1))


def _neighbours(x: SparseTensor, stride: int) -> torch.Tensor | None:
    """``(N, 27)`` rows of every voxel's 3 x 3 x 3 neighbours (-1 absent, offsets in weight order),
    read from the submanifold kernel map the trunk cached for ``x``'s level; None without one."""
    key = ("neighbours", stride)
    if key not in x.cache:
        entry = x.cache.get(f"subm{stride}")
        if not isinstance(entry, SubmEntry) or entry.coords is not x.coords \
                or entry.kernel_size != (3, 3, 3) or entry.dilation != (1, 1, 1):
            return None
        kmap = entry.kmap
        table = torch.full((kmap.num_out, 27), -1, dtype=torch.int64, device=x.coords.device)
        counts = torch.tensor(kmap.bounds, device=x.coords.device).diff()
        offset = torch.repeat_interleave(torch.arange(27, device=x.coords.device), counts)
        table[kmap.out_idx, offset] = kmap.in_idx
        x.cache[key] = table
    return x.cache[key]


def _own_rows(x: SparseTensor, batch: SegBatch, stride: int) -> torch.Tensor | None:
    """Row of ``x`` holding each point's own voxel at ``stride``, following every stride-1 voxel up
    the trunk's cached stride-2 maps (each input feeds exactly one output); None without them.
    Kept in the cache: the corners and the voxelisation at one stride both ask for them."""
    if ("own", stride) in x.cache:
        return x.cache[("own", stride)]
    rows = batch.point_to_voxel
    stem = x.cache.get("subm1")
    level_coords = stem.coords if isinstance(stem, SubmEntry) else None
    for level in range(1, stride.bit_length()):
        entry = x.cache.get(f"down{level}")
        if not isinstance(entry, StridedEntry) or entry.kernel_size != (2, 2, 2) or entry.in_coords is not level_coords:
            return None
        key = ("parent", level)
        if key not in x.cache:
            parent = torch.full((entry.kmap.num_in,), -1, dtype=torch.int64, device=rows.device)
            parent[entry.kmap.in_idx] = entry.kmap.out_idx
            x.cache[key] = parent
        rows, level_coords = x.cache[key][rows], entry.out_coords
    if level_coords is not x.coords:
        return None
    x.cache[("own", stride)] = rows
    return rows


def trilinear_weights(x: SparseTensor, points: torch.Tensor, stride: int,
                      batch: SegBatch | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Neighbour rows ``(P, 8)`` (-1 absent) and weights ``(P, 8)`` of the points.

    ``points``: ``(P, 4)`` float batch, position in stride-1 voxel units. With the ``batch`` the
    points belong to, the rows come from the trunk's cached kernel maps where they can (a gather
    instead of a binary search per corner; the same rows).
    """
    u = points[:, 1:].double() / stride - 0.5
    base = torch.floor(u)
    frac = (u - base).float()
    base = base.long()
    rows = _corner_rows(x, batch, stride, points, base) if batch is not None else None
    if rows is None:
        rows = _lookup_corners(x, points, base)
    # Each corner's weight is the product of one factor per axis, 1 - f or f by the corner's side
    # (corners in _CORNERS' order: first axis major).
    sides = torch.stack([1 - frac, frac], -1)  # (P, 3, 2)
    w = (sides[:, 0, :, None, None] * sides[:, 1, None, :, None] * sides[:, 2, None, None, :]).reshape(-1, 8)
    w = torch.where(rows >= 0, w, torch.zeros_like(w))
    w = w / w.sum(1, keepdim=True).clamp_min(1e-12)
    return rows, w


def _lookup_corners(x: SparseTensor, points: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
    """:func:`_lookup` of the 8 cells ``(P, 8)`` from each point's lowest corner ``base`` ``(P, 3)`` up."""
    return _lookup(x, points[:, 0].long()[:, None].expand(-1, 8), base[:, None, :] + _CORNERS.to(base.device))


class _Interpolate(torch.autograd.Function):
    """``matrix @ feats``, with the transposed matrix for the gradient (both CSR)."""

    @staticmethod
    def forward(ctx, feats: torch.Tensor, matrix: torch.Tensor, transposed: torch.Tensor) -> torch.Tensor:
        ctx.transposed = transposed
        return matrix @ feats

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor):
        return ctx.transposed @ grad.contiguous(), None, None


def interpolation_matrices(rows: torch.Tensor, weights: torch.Tensor, num_voxels: int, transposed: bool = True):
    """The ``(P, N)`` interpolation matrix of ``rows``/``weights`` and its transpose (None unless
    ``transposed``: only a gradient needs it), both CSR."""
    present = rows >= 0
    per_point = present.sum(1)
    cols, values = rows.masked_select(present), weights.masked_select(present)  # point-major, in matrix order
    point_ptr = torch.zeros(len(rows) + 1, dtype=torch.int64, device=rows.device)
    point_ptr[1:] = per_point.cumsum(0)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        matrix = torch.sparse_csr_tensor(point_ptr, cols, values, (len(rows), num_voxels), check_invariants=False)
        if not transposed:
            return matrix, None
        # A stable sort keeps each voxel's points in point order; int32 keys sort in about half the time.
        order = torch.argsort(cols.to(torch.int32) if num_voxels < 2**31 else cols, stable=True)
        points = torch.arange(len(rows), device=rows.device).repeat_interleave(per_point)
        voxel_ptr = torch.zeros(num_voxels + 1, dtype=torch.int64, device=rows.device)
        voxel_ptr[1:] = torch.bincount(cols, minlength=num_voxels).cumsum(0)
        return matrix, torch.sparse_csr_tensor(voxel_ptr, points[order], values[order], (num_voxels, len(rows)),
                                               check_invariants=False)


def devoxelize(x: SparseTensor, rows: torch.Tensor, weights: torch.Tensor, memo: dict | None = None) -> torch.Tensor:
    """Point features ``(P, C)`` interpolated from voxel features.

    ``memo``: a dict kept with ``rows``/``weights`` across reads of the same voxels (SPVCNN reads
    stride 1 twice), so that their sparse matrices are built once."""
    w = weights.to(x.feats.dtype)
    if x.feats.device.type == "cpu" and x.feats.dtype in (torch.float32, torch.float64):
        # One sparse product each way: on a CPU about half the time of eight gathers, whose
        # gradient scatters 8 P rows into few voxels at the coarse strides.
        memo = {} if memo is None else memo
        grad = torch.is_grad_enabled() and x.feats.requires_grad
        matrix, transposed = memo.get(w.dtype, (None, None))
        if matrix is None or (grad and transposed is None):
            matrix, transposed = memo[w.dtype] = interpolation_matrices(rows, w, x.num_voxels, transposed=grad)
        return _Interpolate.apply(x.feats, matrix, transposed) if grad else matrix @ x.feats
    return devoxelize_by_gathers(x, rows, weights)


def devoxelize_by_gathers(x: SparseTensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """:func:`devoxelize` as eight weighted gathers (any device and dtype)."""
    w = weights.to(x.feats.dtype)
    # One corner at a time: never materialises a (P, 8, C) tensor.
    out = None
    for k in range(rows.shape[1]):
        term = x.feats.index_select(0, rows[:, k].clamp_min(0)) * w[:, k, None]
        out = term if out is None else out + term
    return out


def _corner_rows(x: SparseTensor, batch: SegBatch, stride: int, points: torch.Tensor,
                 base: torch.Tensor) -> torch.Tensor | None:
    """:func:`_lookup`'s rows for the 8 cells from ``base`` ``(P, 3)`` up, read from the neighbours of
    each point's own voxel; a point whose corners leave that neighbourhood (its float position
    rounded across a cell boundary) is looked up. None without the cached maps."""
    table, own = _neighbours(x, stride), _own_rows(x, batch, stride)
    if table is None or own is None:
        return None
    # Corners add 0 or 1 per axis, so all 8 lie in the 3 x 3 x 3 neighbourhood exactly when the
    # lowest one is at -1 or 0 from the own voxel on every axis.
    low = base - x.coords.index_select(0, own)[:, 1:].long()
    near = ((low >= -1) & (low <= 0)).all(-1)
    place = torch.tensor([9, 3, 1], device=base.device)
    first = ((low.clamp(-1, 0) + 1) * place).sum(-1)  # neighbour slot of the lowest corner
    offset = first[:, None] + (_CORNERS.to(base.device) * place).sum(-1)  # (P, 8)
    rows = table.view(-1).index_select(0, (own[:, None] * 27 + offset).view(-1)).view(offset.shape)
    if not bool(near.all()):
        far = ~near
        rows[far] = _lookup_corners(x, points[far], base[far])
    return rows


def point_voxel_rows(x: SparseTensor, batch: SegBatch, stride: int) -> torch.Tensor:
    """Row of ``x`` holding each point's own voxel at ``stride``, from the integer
    coordinates of the point's stride-1 voxel (float positions can round across a
    cell boundary and miss it)."""
    rows = _own_rows(x, batch, stride)
    if rows is not None:
        return rows
    own = batch.voxel_coords[batch.point_to_voxel].long()
    cells = torch.div(own[:, 1:], stride, rounding_mode="floor")
    rows = _lookup(x, own[:, 0], cells)
    if (rows < 0).any():
        raise ValueError(f"{int((rows < 0).sum())} points have no voxel at stride {stride}")
    return rows


def voxelize_points(x: SparseTensor, point_feats: torch.Tensor, rows: torch.Tensor) -> SparseTensor:
    """Mean of the point features of each voxel of ``x`` (0 for voxels without points).

    Summed in fp32 whatever the autocast dtype: a stride-16 voxel holds hundreds to thousands of
    points, whose fp16 sum can pass fp16's 65504 (SPVCNN's loss went non-finite under fp16 AMP on an
    H200) and drops increments well before that; the mean is returned in the features' dtype."""
    wide = torch.promote_types(point_feats.dtype, torch.float32)
    total = point_feats.new_zeros((x.num_voxels, point_feats.shape[1]), dtype=wide)
    total.index_add_(0, rows, point_feats.to(wide))
    count = torch.bincount(rows, minlength=x.num_voxels).clamp_min(1).to(wide)
    return x.replace_feats((total / count[:, None]).to(point_feats.dtype))


class SeededDropout(nn.Module):
    """Dropout whose masks come from the module's own seeded generator.

    The stream restarts from ``seed`` on every device it first sees; with
    ``reseed`` a trainer can tie it to its own generator.
    """

    def __init__(self, p: float, seed: int):
        super().__init__()
        if not 0.0 <= p < 1.0:
            raise ValueError(f"dropout probability must be in [0, 1), got {p}")
        self.p = float(p)
        self.seed = int(seed)
        self._generators: dict[str, torch.Generator] = {}

    def reseed(self, seed: int) -> None:
        self.seed = int(seed)
        self._generators.clear()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or self.p == 0.0:
            return x
        key = str(x.device)
        if key not in self._generators:
            self._generators[key] = torch.Generator(device=x.device).manual_seed(self.seed)
        keep = torch.rand(x.shape, generator=self._generators[key], device=x.device) >= self.p
        return x * keep.to(x.dtype) / (1.0 - self.p)

    def extra_repr(self) -> str:
        return f"p={self.p}, seed={self.seed}"


def point_mlp(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(cin, cout), nn.BatchNorm1d(cout), nn.ReLU())


class SPVCNN(nn.Module):
    """Sparse point-voxel CNN; ``forward(batch)`` returns per-point logits ``(P, 19)``."""

    def __init__(self, in_channels: int = 4, num_classes: int = NUM_SEG_CLASSES, width: str = "W32",
                 depth: int = 18, dropout: float = 0.3, backend: str = "auto",
                 device: str | torch.device = "cpu", generator: torch.Generator | None = None):
        super().__init__()
        self.trunk = UNetTrunk(in_channels, width, depth, backend, device)
        stem, enc, dec = self.trunk.stem_channels, self.trunk.encoder_channels, self.trunk.decoder_channels
        self.point_mlps = nn.ModuleList([point_mlp(stem, enc[-1]), point_mlp(enc[-1], dec[1]),
                                         point_mlp(dec[1], dec[3])])
        self.classifier = nn.Linear(dec[3], num_classes)
        init_weights(self, generator)
        # Dropout draws from its own stream, seeded from the init generator.
        seed = int(torch.randint(0, 2**62, (1,), generator=generator)) if generator is not None else 0
        self.dropout = SeededDropout(dropout, seed)

    @property
    def backend(self) -> str:
        return self.trunk.backend

    def forward(self, batch: SegBatch) -> torch.Tensor:
        t = self.trunk
        pts = batch.point_coords
        x0 = t.stem(network_input(batch))
        interp = {}  # stride -> (rows, weights, memo); stride 1 is read twice

        def read(x: SparseTensor, stride: int) -> torch.Tensor:
            if stride not in interp:
                interp[stride] = (*trilinear_weights(x, pts, stride, batch), {})
            return devoxelize(x, *interp[stride])

        z0 = read(x0, 1)
        x = voxelize_points(x0, z0, batch.point_to_voxel)  # stride 1: the points' own voxels
        skips = [x]
        for stage in t.encoder:
            x = stage(x)
            skips.append(x)
        z1 = read(x, 16) + self.point_mlps[0](z0)
        x = voxelize_points(x, z1, point_voxel_rows(x, batch, 16))
        x = x.replace_feats(self.dropout(x.feats))
        for i in range(2):
            x = t.fuse[i](concat(t.up[i](x), skips[3 - i]))
        z2 = read(x, 4) + self.point_mlps[1](z1)
        x = voxelize_points(x, z2, point_voxel_rows(x, batch, 4))
        x = x.replace_feats(self.dropout(x.feats))
        for i in range(2, 4):
            x = t.fuse[i](concat(t.up[i](x), skips[3 - i]))
        z3 = read(x, 1) + self.point_mlps[2](z2)
        return self.classifier(z3)


def spvcnn(variant: str = "W32", **kwargs) -> SPVCNN:
    """Build ``W16``, ``W20``, ``W32`` (depth 18) or ``SPVCNN34`` (W32, deeper encoder)."""
    if variant == "SPVCNN34":
        return SPVCNN(width="W32", depth=34, **kwargs)
    return SPVCNN(width=variant, depth=18, **kwargs)
