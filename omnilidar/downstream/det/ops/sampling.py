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

import torch
from torch import nn

from omnilidar.downstream.det.ops.points import pairs_within_squares

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


def _first_hits(hit: torch.Tensor, values: torch.Tensor, nsample: int):
    """Per row of ``hit`` (R, K) bool: the ``values`` (R, K) at the first
    ``nsample`` hits in column order, padded with the first hit's value.
    Returns (idx (R, nsample) long, empty (R,) bool); empty rows give 0."""
    k = hit.shape[1]
    key = torch.where(hit, torch.arange(k, device=hit.device), k)
    first = torch.topk(key, min(nsample, k), dim=1, largest=False, sorted=True).values
    if first.shape[1] < nsample:  # fewer candidates than samples: pad the columns
        first = torch.cat([first, first.new_full((len(first), nsample - first.shape[1]), k)], dim=1)
    picked = torch.gather(values, 1, first.clamp(max=k - 1))
    picked = torch.where(first < k, picked, picked[:, :1])
    empty = ~hit.any(dim=1)
    return torch.where(empty[:, None], 0, picked), empty


def _batch_starts(counts: torch.Tensor) -> list[int]:
    return list(itertools.accumulate(counts.tolist(), initial=0))


def _first_in_index_order(ip: torch.Tensor, ic: torch.Tensor, n: int, m: int, nsample: int):
    """From hit pairs (point ip, centre ic), each centre's ``nsample`` lowest point
    indices, padded with its first; (idx (m, nsample), empty (m,)), empty rows 0."""
    key, _ = torch.sort(ic * max(n, 1) + ip)
    ic, ip = key // max(n, 1), key % max(n, 1)
    counts = torch.bincount(ic, minlength=m)
    rank = torch.arange(len(key), device=key.device) - (torch.cumsum(counts, 0) - counts)[ic]
    keep = rank < nsample
    idx = torch.zeros(m, nsample, dtype=torch.long, device=key.device)
    idx[ic[keep], rank[keep]] = ip[keep]
    filled = torch.arange(nsample, device=key.device) < counts[:, None]
    return torch.where(filled, idx, idx[:, :1]), counts == 0


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


def voxel_query(max_range, radius: float, nsample: int, xyz: torch.Tensor, new_xyz: torch.Tensor,
                new_coords: torch.Tensor, point_indices: torch.Tensor):
    """Voxel R-CNN's voxel query: neighbours of each centre among the voxels around
    its own voxel.

    ``max_range`` (z, y, x) half-widths of the voxel window; ``new_coords`` (M, 4)
    [batch, z, y, x] of each centre's voxel; ``point_indices`` (B, Z, Y, X) the
    index into ``xyz`` of each voxel's point, -1 where empty. Voxels are scanned
    z, then y, then x from -range to +range; a voxel counts when its point lies
    within ``radius`` (squared distance <= radius^2). Returns (idx (M, nsample)
    long: the first ``nsample`` such point indices, padded with the first one;
    empty_ball_mask (M,)), empty windows giving zeros.
    """
    zr, yr, xr = (int(r) for r in max_range)
    _, nz, ny, nx = point_indices.shape
    dev = new_xyz.device
    grid = torch.meshgrid(torch.arange(-zr, zr + 1, device=dev), torch.arange(-yr, yr + 1, device=dev),
                          torch.arange(-xr, xr + 1, device=dev), indexing="ij")
    offsets = torch.stack([g.reshape(-1) for g in grid], dim=1)  # (K, 3) in scan order
    k = len(offsets)
    flat_map = point_indices.reshape(-1).long()
    size = torch.tensor([nz, ny, nx], device=dev)
    idx = torch.zeros(len(new_xyz), nsample, dtype=torch.long, device=dev)
    empty = torch.ones(len(new_xyz), dtype=torch.bool, device=dev)
    r = torch.tensor(radius, dtype=xyz.dtype)
    r2 = (r * r).item()  # squared in the input dtype, as the kernel does
    rows = max(1, _CHUNK.get(dev.type, _CHUNK_DEFAULT) // k)
    for c0 in range(0, len(new_xyz), rows):
        c1 = min(len(new_xyz), c0 + rows)
        coords = new_coords[c0:c1].long()
        cell = coords[:, None, 1:] + offsets[None]  # (R, K, 3) z y x
        inside = ((cell >= 0) & (cell < size)).all(dim=2)
        cell = torch.where(inside[..., None], cell, 0)
        lin = ((coords[:, None, 0] * nz + cell[..., 0]) * ny + cell[..., 1]) * nx + cell[..., 2]
        neighbour = torch.where(inside, flat_map[lin], -1)
        pts = xyz[neighbour.clamp(min=0)]
        ctr = new_xyz[c0:c1, None]
        d2 = ((pts[..., 0] - ctr[..., 0]) ** 2 + (pts[..., 1] - ctr[..., 1]) ** 2
              + (pts[..., 2] - ctr[..., 2]) ** 2)
        idx[c0:c1], empty[c0:c1] = _first_hits((neighbour >= 0) & (d2 <= r2), neighbour, nsample)
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
