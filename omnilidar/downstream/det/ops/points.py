"""Which points lie inside which lidar boxes (N points x M boxes), any device.

A point is inside a box when, in the box's own frame, |x| <= dx/2, |y| <= dy/2
and |z - z_center| <= dz/2: faces count as inside. (OpenPCDet's CUDA
points_in_boxes excludes the four side faces; the two differ only for points
exactly on a face.) A cheap axis-aligned test against each box's bounding square
picks candidate pairs in chunks, and the exact rotated test runs in float64 on
those only, so the cost is O(N M) compares plus work near the boxes, with no
(N, M) float temporaries.
"""

from __future__ import annotations

import torch

_CHUNK = 1 << 22  # (points x boxes) prefilter entries per batch
_MARGIN = 1e-3  # slack (m) of the prefilter; the exact test decides


def _check(points: torch.Tensor, boxes: torch.Tensor) -> None:
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must be (N, >=3), got {tuple(points.shape)}")
    if boxes.ndim != 2 or boxes.shape[1] < 7:
        raise ValueError(f"boxes must be (M, 7), got {tuple(boxes.shape)}")


def _inside_pairs(points: torch.Tensor, boxes: torch.Tensor):
    """Yield (point index, box index) of every point-inside-box pair, chunk by chunk."""
    n, m = len(points), len(boxes)
    if n == 0 or m == 0:
        return
    b = boxes[:, :7].to(device=points.device, dtype=torch.float64)
    reach = 0.5 * torch.hypot(b[:, 3], b[:, 4])
    # Float32 prefilter; the margin covers rounding of coordinates up to 1e5 m.
    slack = (_MARGIN + 2e-7 * (b[:, 0:2].abs().amax(dim=1) + reach)).float()
    cx, cy, reach32 = b[:, 0].float(), b[:, 1].float(), reach.float() + slack
    cos, sin = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    rows = max(1, _CHUNK // m)
    for r0 in range(0, n, rows):
        p = points[r0:r0 + rows]
        x, y = p[:, 0].float(), p[:, 1].float()
        near = ((x[:, None] - cx).abs() <= reach32) & ((y[:, None] - cy).abs() <= reach32)
        ip, ib = torch.nonzero(near, as_tuple=True)
        q = p[ip, :3].to(torch.float64)
        ox, oy = q[:, 0] - b[ib, 0], q[:, 1] - b[ib, 1]
        inside = (
            ((ox * cos[ib] + oy * sin[ib]).abs() <= 0.5 * b[ib, 3])
            & ((oy * cos[ib] - ox * sin[ib]).abs() <= 0.5 * b[ib, 4])
            & ((q[:, 2] - b[ib, 2]).abs() <= 0.5 * b[ib, 5])
        )
        yield ip[inside] + r0, ib[inside]


def points_in_boxes_mask(points: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """(N, M) bool: point n (points (N, >=3), x y z used) lies in box m (boxes (M, 7))."""
    _check(points, boxes)
    out = torch.zeros(len(points), len(boxes), dtype=torch.bool, device=points.device)
    for ip, ib in _inside_pairs(points, boxes):
        out[ip, ib] = True
    return out


def points_in_boxes(points: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """(N,) long: index of the first (lowest-index) box containing each point, -1 if none,
    as OpenPCDet's points_in_boxes_gpu for one sample."""
    _check(points, boxes)
    m = len(boxes)
    first = torch.full((len(points),), m, dtype=torch.long, device=points.device)
    for ip, ib in _inside_pairs(points, boxes):
        first.scatter_reduce_(0, ip, ib, reduce="amin")
    return torch.where(first < m, first, -1)
