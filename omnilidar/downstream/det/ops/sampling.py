"""Point sampling and neighbourhood grouping with OpenPCDet's semantics
(pcdet.ops.pointnet2.pointnet2_stack), in plain PyTorch on any device.

"Stack" layout: the points of all samples are concatenated, (N1 + N2 + ..., 3),
with per-sample counts ``*_batch_cnt`` (B,). Ball-query indices are local to
their sample (0 .. N_b - 1); voxel-query indices are whatever the voxel -> point
map holds (global there). Empty neighbourhoods come back as index 0 with
``empty_ball_mask`` set, exactly as the CUDA ops return them.

Everything is vectorised, in chunks of bounded size: ball queries look only at
the points near each centre (a sorted-strip search shared with points in
boxes), voxel queries at the voxels of each centre's window.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import torch
from torch import nn

from omnilidar.geometry.points_in_boxes import expand_runs, pairs_within_squares
from omnilidar.sparse.tensor import pack_coords

# (centre, window voxel) pairs per voxel-query batch: ~80 MB of scratch on CPU.
_CHUNK = {"cpu": 1 << 20}
_CHUNK_DEFAULT = 1 << 23
_SQUARE_MARGIN = 1e-3  # m added to the candidate squares; the distance test decides


def farthest_point_sample(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
    """(B, npoint) long indices of iterative farthest point sampling of (B, N, 3).

    Starts at index 0 and each step takes the point farthest (squared distance,
    computed in the input dtype like the CUDA kernel) from those chosen so far;
    ties go to the lowest index. Once every point is chosen the remaining
    picks repeat index 0, as the CUDA op does.
    """
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise ValueError(f"xyz must be (B, N, 3), got {tuple(xyz.shape)}")
    b, n, _ = xyz.shape
    out = torch.zeros(b, npoint, dtype=torch.long, device=xyz.device)
    if n == 0 or npoint <= 1:
        return out
    x, y, z = (xyz[..., k].contiguous() for k in range(3))
    nearest = torch.full((b, n), 1e10, dtype=xyz.dtype, device=xyz.device)
    rows = torch.arange(b, device=xyz.device)
    last = out[:, 0]
    picks = [last]
    for _ in range(1, npoint):
        p = xyz[rows, last]  # (B, 3) the point chosen last
        dx, dy, dz = x - p[:, 0:1], y - p[:, 1:2], z - p[:, 2:3]
        torch.minimum(nearest, dx * dx + dy * dy + dz * dz, out=nearest)
        last = torch.argmax(nearest, dim=1)
        picks.append(last)
    return torch.stack(picks, dim=1)


def _first_per_row(row: torch.Tensor, value: torch.Tensor, m: int, nsample: int):
    """From hits sorted by ``row`` (and in the wanted order within a row), each of the
    ``m`` rows' first ``nsample`` values, padded with its first; (idx (m, nsample)
    long, empty (m,) bool), empty rows giving zeros."""
    counts = torch.bincount(row, minlength=m)
    rank = torch.arange(len(row), device=row.device) - (torch.cumsum(counts, 0) - counts)[row]
    keep = rank < nsample
    idx = torch.zeros(m, nsample, dtype=torch.long, device=row.device)
    idx[row[keep], rank[keep]] = value[keep]
    filled = torch.arange(nsample, device=row.device) < counts[:, None]
    return torch.where(filled, idx, idx[:, :1]), counts == 0


def _batch_starts(counts: torch.Tensor) -> list[int]:
    return list(itertools.accumulate(counts.tolist(), initial=0))


def _first_in_index_order(ip: torch.Tensor, ic: torch.Tensor, n: int, m: int, nsample: int):
    """From hit pairs (point ip, centre ic), each centre's ``nsample`` lowest point
    indices, padded with its first; (idx (m, nsample), empty (m,)), empty rows 0."""
    key, _ = torch.sort(ic * max(n, 1) + ip)
    return _first_per_row(key // max(n, 1), key % max(n, 1), m, nsample)


def ball_query(radius: float, nsample: int, xyz: torch.Tensor, xyz_batch_cnt: torch.Tensor,
               new_xyz: torch.Tensor, new_xyz_batch_cnt: torch.Tensor):
    """Stack ball query: for each centre of ``new_xyz`` (M, 3), the first ``nsample``
    points of its own sample, in index order, with squared distance < radius^2
    (computed in the input dtype, as the CUDA kernel).

    Returns (idx (M, nsample) long, local to the sample; empty_ball_mask (M,) bool).
    A ball with fewer points repeats its first one; an empty ball gives zeros
    and sets the mask. Candidates come from a sorted-strip search around each
    centre (``points.pairs_within_squares``), not from all N x M pairs.
    """
    if len(xyz_batch_cnt) != len(new_xyz_batch_cnt):
        raise ValueError("xyz_batch_cnt and new_xyz_batch_cnt must have one count per sample")
    p_start, c_start = _batch_starts(xyz_batch_cnt), _batch_starts(new_xyz_batch_cnt)
    if p_start[-1] != len(xyz) or c_start[-1] != len(new_xyz):
        raise ValueError(f"batch counts sum to {p_start[-1]} points / {c_start[-1]} centres, "
                         f"got {len(xyz)} / {len(new_xyz)}")
    idx = torch.zeros(len(new_xyz), nsample, dtype=torch.long, device=new_xyz.device)
    empty = torch.ones(len(new_xyz), dtype=torch.bool, device=new_xyz.device)
    r = torch.tensor(radius, dtype=xyz.dtype)
    r2 = (r * r).item()  # squared in the input dtype, as the kernel does
    for b in range(len(p_start) - 1):
        pts, ctr = xyz[p_start[b]:p_start[b + 1]], new_xyz[c_start[b]:c_start[b + 1]]
        if len(pts) == 0 or len(ctr) == 0:
            continue
        reach = torch.full((len(ctr),), radius * (1 + 1e-6) + _SQUARE_MARGIN, dtype=torch.float64,
                           device=ctr.device)
        hits_p, hits_c = [], []
        for ip, ic in pairs_within_squares(pts, ctr[:, :2].to(torch.float64), reach):
            d2 = ((ctr[ic, 0] - pts[ip, 0]) ** 2 + (ctr[ic, 1] - pts[ip, 1]) ** 2
                  + (ctr[ic, 2] - pts[ip, 2]) ** 2)
            hit = d2 < r2
            hits_p.append(ip[hit])
            hits_c.append(ic[hit])
        if hits_p:
            rows = slice(c_start[b], c_start[b + 1])
            idx[rows], empty[rows] = _first_in_index_order(torch.cat(hits_p), torch.cat(hits_c),
                                                           len(pts), len(ctr), nsample)
    return idx, empty


def grouping_operation(features: torch.Tensor, features_batch_cnt: torch.Tensor,
                       idx: torch.Tensor, idx_batch_cnt: torch.Tensor) -> torch.Tensor:
    """(M, C, nsample) features (N, C) gathered at sample-local ``idx`` (M, nsample);
    differentiable (gradients add up at repeated indices)."""
    starts = torch.cumsum(features_batch_cnt.to(idx.device), 0) - features_batch_cnt.to(idx.device)
    owner = torch.repeat_interleave(torch.arange(len(idx_batch_cnt), device=idx.device),
                                    idx_batch_cnt.to(idx.device), output_size=len(idx))
    flat = idx.long() + starts[owner][:, None]
    return features[flat].permute(0, 2, 1).contiguous()


def query_and_group(radius: float, nsample: int, xyz: torch.Tensor, xyz_batch_cnt: torch.Tensor,
                    new_xyz: torch.Tensor, new_xyz_batch_cnt: torch.Tensor,
                    features: torch.Tensor | None = None, use_xyz: bool = True):
    """Ball query + grouping: (new_features (M, 3 + C, nsample), idx, empty_ball_mask).

    The first 3 channels are the neighbours' xyz relative to the centre (when
    ``use_xyz``), then their features; empty balls are all zero.
    """
    idx, empty = ball_query(radius, nsample, xyz, xyz_batch_cnt, new_xyz, new_xyz_batch_cnt)
    grouped_xyz = grouping_operation(xyz, xyz_batch_cnt, idx, new_xyz_batch_cnt) - new_xyz[..., None]
    grouped_xyz = torch.where(empty[:, None, None], 0.0, grouped_xyz)
    if features is None:
        if not use_xyz:
            raise ValueError("query_and_group needs features or use_xyz")
        return grouped_xyz, idx, empty
    grouped = grouping_operation(features, xyz_batch_cnt, idx, new_xyz_batch_cnt)
    grouped = torch.where(empty[:, None, None], 0.0, grouped)
    return (torch.cat([grouped_xyz, grouped], dim=1) if use_xyz else grouped), idx, empty


class QueryAndGroup(nn.Module):
    """OpenPCDet's pointnet2_stack QueryAndGroup (no parameters):
    forward(...) -> (new_features (M, 3 + C, nsample), idx)."""

    def __init__(self, radius: float, nsample: int, use_xyz: bool = True):
        super().__init__()
        self.radius, self.nsample, self.use_xyz = radius, nsample, use_xyz

    def forward(self, xyz, xyz_batch_cnt, new_xyz, new_xyz_batch_cnt, features=None):
        new_features, idx, _ = query_and_group(self.radius, self.nsample, xyz, xyz_batch_cnt,
                                               new_xyz, new_xyz_batch_cnt, features, self.use_xyz)
        return new_features, idx


class VoxelMap(NamedTuple):
    """Sparse form of a voxel -> point map: the occupied cells' linear (b, z, y, x)
    indices, ascending, and the point index each holds, over a (B, Z, Y, X) grid."""

    shape: tuple[int, int, int, int]
    cells: torch.Tensor
    points: torch.Tensor

    @classmethod
    def from_dense(cls, point_indices: torch.Tensor) -> "VoxelMap":
        """From OpenPCDet's dense (B, Z, Y, X) map, -1 where empty."""
        flat = point_indices.reshape(-1)
        cells = torch.nonzero(flat >= 0).squeeze(1)
        return cls(tuple(point_indices.shape), cells, flat[cells].long())

    @classmethod
    def from_coords(cls, coords: torch.Tensor, shape) -> "VoxelMap":
        """From (N, 4) [b, z, y, x] voxel coordinates; voxel i holds point i."""
        cells, order = torch.sort(pack_coords(coords, shape[1:]))
        return cls(tuple(int(n) for n in shape), cells, order)


def _distinct_voxels(coords: torch.Tensor, size, reach):
    """Distinct rows of (M, 4) [b, z, y, x] ``coords`` (those more than ``reach`` + 1
    cells outside the (z, y, x) grid ``size`` clamped to that margin, which leaves
    their windows empty), and each row's index among them."""
    pad = torch.tensor(reach, device=coords.device) + 1
    size = torch.tensor(size, device=coords.device)
    c = coords.long().clone()
    c[:, 1:] = torch.minimum(torch.maximum(c[:, 1:], -pad), size - 1 + pad)
    span = size + 2 * pad
    key = c[:, 0]
    for axis in range(3):
        key = key * span[axis] + c[:, axis + 1] + pad[axis]
    key, owner = torch.unique(key, return_inverse=True)
    voxels = c.new_empty((len(key), 4))
    voxels[owner] = c
    return voxels, owner


def voxel_query(max_range, radius: float, nsample: int, xyz: torch.Tensor, new_xyz: torch.Tensor,
                new_coords: torch.Tensor, point_indices: torch.Tensor | VoxelMap):
    """Voxel R-CNN's voxel query: neighbours of each centre among the voxels around
    its own voxel.

    ``max_range`` (z, y, x) half-widths of the voxel window; ``new_coords`` (M, 4)
    [batch, z, y, x] of each centre's voxel; ``point_indices`` the index into
    ``xyz`` of each voxel's point: OpenPCDet's dense (B, Z, Y, X) map, -1 where
    empty, or the same as a :class:`VoxelMap`. Voxels are scanned z, then y, then
    x from -range to +range; a voxel counts when its point lies within ``radius``
    (squared distance <= radius^2). Returns (idx (M, nsample) long: the first
    ``nsample`` such point indices, padded with the first one; empty_ball_mask
    (M,)), empty windows giving zeros.

    Only occupied voxels are visited: in (batch, z, y, x) order each (z, y) row of
    a window is one contiguous run, found by binary search, so runs taken row by
    row come out in the kernel's scan order. Windows are looked up once per
    distinct centre voxel (a RoI's grid points share voxels).
    """
    voxel_map = point_indices if isinstance(point_indices, VoxelMap) else VoxelMap.from_dense(point_indices)
    zr, yr, xr = (int(r) for r in max_range)
    _, nz, ny, nx = voxel_map.shape
    dev = new_xyz.device
    m = len(new_xyz)
    idx = torch.zeros(m, nsample, dtype=torch.long, device=dev)
    empty = torch.ones(m, dtype=torch.bool, device=dev)
    if m == 0:
        return idx, empty
    occupied, occupied_point = voxel_map.cells, voxel_map.points
    r = torch.tensor(radius, dtype=xyz.dtype)
    r2 = (r * r).item()  # squared in the input dtype, as the kernel does
    voxels, owner = _distinct_voxels(new_coords, (nz, ny, nx), (zr, yr, xr))
    # One run of occupied voxels per (centre voxel, dz, dy) row of its window.
    dz = torch.arange(-zr, zr + 1, device=dev)[None, :, None]
    dy = torch.arange(-yr, yr + 1, device=dev)[None, None, :]
    b, z, y, x = (voxels[:, i, None, None] for i in range(4))
    z, y = z + dz, y + dy
    row = ((b * nz + z) * ny + y) * nx
    lo = torch.searchsorted(occupied, (row + (x - xr).clamp(min=0)).reshape(-1))
    hi = torch.searchsorted(occupied, (row + (x + xr).clamp(max=nx - 1)).reshape(-1), right=True)
    inside = ((z >= 0) & (z < nz) & (y >= 0) & (y < ny)).reshape(-1)
    runs = torch.where(inside, (hi - lo).clamp(min=0), 0)
    row_voxel = torch.arange(len(voxels), device=dev).repeat_interleave(runs.numel() // len(voxels))
    position, found_voxel = expand_runs(lo, runs, row_voxel)
    found_point = occupied_point[position]
    # Drop neighbours farther than the radius from the box around all centres of their
    # voxel (a bound, with a margin for rounding; the exact test per centre follows).
    corner_lo = torch.full((len(voxels), 3), torch.inf, dtype=torch.float64, device=dev)
    corner_hi = torch.full((len(voxels), 3), -torch.inf, dtype=torch.float64, device=dev)
    centres = new_xyz.to(torch.float64)
    spread = owner[:, None].expand(-1, 3)
    corner_lo.scatter_reduce_(0, spread, centres, "amin")
    corner_hi.scatter_reduce_(0, spread, centres, "amax")
    p = xyz[found_point].to(torch.float64)
    gap = (corner_lo[found_voxel] - p).clamp(min=0) + (p - corner_hi[found_voxel]).clamp(min=0)
    near = (gap * gap).sum(1) <= r2 * (1 + 1e-4) + 1e-9
    found_voxel, found_point = found_voxel[near], found_point[near]
    per_voxel = torch.bincount(found_voxel, minlength=len(voxels))
    first = torch.cumsum(per_voxel, 0) - per_voxel
    # Pair each centre with its voxel's occupied neighbours, in chunks of centres.
    per_centre = per_voxel[owner]
    ends = torch.cumsum(per_centre, 0)
    budget = _CHUNK.get(dev.type, _CHUNK_DEFAULT)
    c0 = 0
    while c0 < m:
        base = int(ends[c0 - 1]) if c0 else 0
        c1 = min(m, max(c0 + 1, int(torch.searchsorted(ends, base + budget, right=True))))
        position, centre = expand_runs(first[owner[c0:c1]], per_centre[c0:c1], torch.arange(c0, c1, device=dev))
        point = found_point[position]
        pts, ctr = xyz[point], new_xyz[centre]
        d2 = ((pts[:, 0] - ctr[:, 0]) ** 2 + (pts[:, 1] - ctr[:, 1]) ** 2 + (pts[:, 2] - ctr[:, 2]) ** 2)
        hit = d2 <= r2
        idx[c0:c1], empty[c0:c1] = _first_per_row(centre[hit] - c0, point[hit], c1 - c0, nsample)
        c0 = c1
    return idx, empty


class VoxelQueryAndGrouping(nn.Module):
    """OpenPCDet's voxel_query_utils.VoxelQueryAndGrouping (no parameters):
    forward(...) -> (grouped_features (M, C, nsample), grouped_xyz (M, 3, nsample),
    empty_ball_mask). ``voxel2point_indices`` holds global (stacked) point indices;
    they are made sample-local per centre before grouping; grouped_xyz is absolute."""

    def __init__(self, max_range, radius: float, nsample: int):
        super().__init__()
        self.max_range, self.radius, self.nsample = max_range, radius, nsample

    def forward(self, new_coords, xyz, xyz_batch_cnt, new_xyz, new_xyz_batch_cnt, features, voxel2point_indices):
        idx, empty = voxel_query(self.max_range, self.radius, self.nsample, xyz, new_xyz,
                                 new_coords, voxel2point_indices)
        starts = torch.cumsum(xyz_batch_cnt.to(idx.device), 0) - xyz_batch_cnt.to(idx.device)
        owner = torch.repeat_interleave(torch.arange(len(new_xyz_batch_cnt), device=idx.device),
                                        new_xyz_batch_cnt.to(idx.device), output_size=len(idx))
        idx = torch.where(empty[:, None], 0, idx - starts[owner][:, None])
        grouped_xyz = grouping_operation(xyz, xyz_batch_cnt, idx, new_xyz_batch_cnt)
        grouped_features = grouping_operation(features, xyz_batch_cnt, idx, new_xyz_batch_cnt)
        return grouped_features, grouped_xyz, empty
