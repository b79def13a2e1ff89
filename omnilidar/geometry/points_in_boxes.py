"""Which points lie inside which lidar boxes (N points x M boxes), any device.

A point is inside a box when, in the box's own frame, |x| <= dx/2, |y| <= dy/2
and |z - z_center| <= dz/2: faces count as inside. (OpenPCDet's CUDA
points_in_boxes also takes points up to 1e-5 m outside the four side faces;
the two differ only within that sliver.) Candidates come from each box's
bounding square (points sorted once by x strip and y, binary searches per
box), and the exact rotated test runs in float64 on those only: O(N log N)
plus work proportional to the points near boxes, no (N, M) temporaries.
"""

from __future__ import annotations

import torch

_CHUNK = 1 << 22  # candidate (point, box) pairs per batch
_MARGIN = 1e-3  # slack (m) of the bounding squares; the exact test decides
_MIN_STRIP = 0.1  # m, narrowest x strip of the sorted layout
_Y_STEP = 1e-3  # m, y resolution of the sort key
_Y_LEVELS = 1 << 32  # y levels per strip (4e6 m of y span); key = strip * (levels + 1) + level


def _check(points: torch.Tensor, boxes: torch.Tensor) -> None:
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must be (N, >=3), got {tuple(points.shape)}")
    if boxes.ndim != 2 or boxes.shape[1] < 7:
        raise ValueError(f"boxes must be (M, 7), got {tuple(boxes.shape)}")


def _box_groups(counts: list[int], budget: int):
    """Consecutive slices of ``counts`` whose sums stay near ``budget``."""
    start, total = 0, 0
    for j, c in enumerate(counts):
        if total and total + c > budget:
            yield slice(start, j)
            start, total = j, 0
        total += c
    if start < len(counts):
        yield slice(start, len(counts))


def expand_runs(first: torch.Tensor, counts: torch.Tensor, owners: torch.Tensor):
    """Flatten runs [first, first + count) into (position, owner) pairs."""
    total = int(counts.sum())
    owner = torch.repeat_interleave(owners, counts, output_size=total)
    run_start = torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts, output_size=total)
    return torch.repeat_interleave(first, counts, output_size=total) + (
        torch.arange(total, device=counts.device) - run_start), owner


def pairs_within_squares(points: torch.Tensor, centre: torch.Tensor, reach: torch.Tensor):
    """Yield (point index, centre index) chunks covering every point (N, >=2) with
    |x - cx| <= reach and |y - cy| <= reach for centres (M, 2) float64 and reach
    (M,) float64: a superset, for an exact test to follow.

    Points are sorted once by (x strip, y), so a box's candidates are one
    contiguous run per strip it spans, found by binary search; every step is a
    monotone rounding, so no point of the square is missed.
    """
    m, dev = len(centre), points.device
    x, y = points[:, 0].to(torch.float64), points[:, 1].to(torch.float64)
    width = max(float(2 * reach.median()), _MIN_STRIP)
    x0, y0 = x.min(), y.min()

    def strip(v):
        return torch.floor((v - x0) / width).long()

    def level(v):  # y in _Y_STEP units, clamped to the key's low bits
        return torch.floor((v - y0) / _Y_STEP).clamp(-1, _Y_LEVELS).long()

    keys, order = torch.sort(strip(x) * (_Y_LEVELS + 1) + level(y))
    s_lo = strip(centre[:, 0] - reach).clamp(min=0)
    s_hi = strip(centre[:, 0] + reach)
    spans = (s_hi - s_lo + 1).clamp(min=0)
    s, box = expand_runs(s_lo, spans, torch.arange(m, device=dev))
    lo = torch.searchsorted(keys, s * (_Y_LEVELS + 1) + level(centre[box, 1] - reach[box]))
    hi = torch.searchsorted(keys, s * (_Y_LEVELS + 1) + level(centre[box, 1] + reach[box]), right=True)
    counts = (hi - lo).clamp(min=0)
    for g in _box_groups(counts.tolist(), _CHUNK):
        if int(counts[g].sum()):
            pos, ib = expand_runs(lo[g], counts[g], box[g])
            yield order[pos], ib


def _inside_pairs(points: torch.Tensor, boxes: torch.Tensor):
    """Yield (point index, box index) of every point-inside-box pair, chunk by chunk."""
    if len(points) == 0 or len(boxes) == 0:
        return
    b = boxes[:, :7].to(device=points.device, dtype=torch.float64)
    reach = 0.5 * torch.hypot(b[:, 3], b[:, 4]) + _MARGIN
    cos, sin = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    for ip, ib in pairs_within_squares(points, b[:, :2], reach):
        q = points[ip, :3].to(torch.float64)
        ox, oy = q[:, 0] - b[ib, 0], q[:, 1] - b[ib, 1]
        inside = (
            ((ox * cos[ib] + oy * sin[ib]).abs() <= 0.5 * b[ib, 3])
            & ((oy * cos[ib] - ox * sin[ib]).abs() <= 0.5 * b[ib, 4])
            & ((q[:, 2] - b[ib, 2]).abs() <= 0.5 * b[ib, 5])
        )
        yield ip[inside], ib[inside]


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
