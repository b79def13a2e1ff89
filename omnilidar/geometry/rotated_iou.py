"""Rotated box overlaps and IoU (bird's-eye view and 3D), exact polygon clipping.

Every pair's intersection is computed in the frame of its first rectangle
(centred on it, axes along its sides), where that rectangle is the axis-aligned
[-ex, ex] x [-ey, ey]: the second rectangle's corners are clipped against those
four half-planes (Sutherland-Hodgman) and the area of what is left comes from
the shoelace formula. All of it runs in float64 on fixed-size vertex buffers,
vectorised over the pairs, so it is device-agnostic and exact where it must be:
identical boxes give IoU 1, nearly parallel boxes far from the origin lose no
digits to their absolute position, zero-size boxes give 0, never NaN.

Pairs whose circumscribed circles do not meet are skipped, and the clipped
pairs are processed in chunks, so N x M never allocates more than an (N, M)
result plus bounded scratch.
"""

from __future__ import annotations

import math

import torch

# Vertex capacity after each clipping step: exact arithmetic needs 5, 6, 7, 8
# (one more per step); the slack is for near-duplicate vertices that rounding
# could create where edges (nearly) coincide. Adversarial nearly parallel and
# edge-sharing pairs at 1e3 m never went past 5, 6, 7, 8.
_CAPACITIES = (6, 8, 10, 12)
# Work per vectorised batch, cache-sized on CPU, large on GPUs: clipped pairs,
# and (N, M) entries of the circle prefilter.
_PAIR_CHUNK = {"cpu": 1 << 13}
_PAIR_CHUNK_DEFAULT = 1 << 18
_PREFILTER_CHUNK = {"cpu": 1 << 18}
_PREFILTER_CHUNK_DEFAULT = 1 << 24
# Union floors, as OpenPCDet's iou3d_nms (BEV kernel 1e-8, 3D 1e-6).
_BEV_EPS = 1e-8
_VOLUME_EPS = 1e-6
# Corner signs, counter-clockwise from (+ex, +ey).
_CORNER_SIGNS = ((1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0))


def _check_boxes(boxes: torch.Tensor, width: int, name: str) -> None:
    if not torch.is_tensor(boxes) or boxes.ndim != 2 or boxes.shape[1] < width:
        shape = tuple(boxes.shape) if torch.is_tensor(boxes) else type(boxes).__name__
        raise ValueError(f"{name} must be an (N, {width}) tensor, got {shape}")
    if not boxes.is_floating_point():
        raise ValueError(f"{name} must be floating point, got {boxes.dtype}")


def _result_dtype(a: torch.Tensor, b: torch.Tensor) -> torch.dtype:
    return torch.promote_types(a.dtype, b.dtype)


def _next_slots(count: torch.Tensor, s: int) -> torch.Tensor:
    """(P, s) index of each slot's successor around a polygon of ``count`` vertices."""
    slots = torch.arange(1, s + 1, device=count.device)
    return torch.where(slots < count[:, None], slots, 0)


def _clip_half_plane(u, w, count, sign: float, bound, capacity: int):
    """Keep the part of each polygon where ``sign * u <= bound``.

    Polygons are given by their clipped coordinate ``u`` and the other one ``w``,
    (P, S) each, with ``count`` (P,) vertices in order (later slots are filler).
    Returns (u, w) as (P, capacity) and the new counts.
    """
    p, s = u.shape
    real = torch.arange(s, device=u.device) < count[:, None]
    nxt = _next_slots(count, s)
    dist = bound[:, None] - sign * u  # >= 0 inside
    dist_next = torch.gather(dist, 1, nxt)
    inside = dist >= 0
    keep = real & inside
    cross = real & (inside != (dist_next >= 0))
    # Crossing edges have distances of opposite sign, so the denominator is > 0;
    # the crossing lies on the line exactly (u = sign * bound).
    t = dist / torch.where(cross, dist - dist_next, 1.0)
    w_hit = torch.lerp(w, torch.gather(w, 1, nxt), t)
    # Sutherland-Hodgman order: each vertex (if inside), then its edge's crossing.
    emitted = keep.to(torch.int32) + cross.to(torch.int32)
    first = torch.cumsum(emitted, dim=1, dtype=torch.int32) - emitted
    spill = capacity  # slots past capacity land in a discarded column
    at_keep = torch.where(keep, first, spill).clamp(max=spill).long()
    at_cross = torch.where(cross, first + keep.to(torch.int32), spill).clamp(max=spill).long()
    out_u = u.new_zeros(p, capacity + 1)
    out_w = u.new_zeros(p, capacity + 1)
    out_u.scatter_(1, at_keep, u)
    out_w.scatter_(1, at_keep, w)
    out_u.scatter_(1, at_cross, (sign * bound)[:, None].expand(-1, s))
    out_w.scatter_(1, at_cross, w_hit)
    return out_u[:, :capacity], out_w[:, :capacity], emitted.sum(dim=1).clamp(max=capacity)


def _polygon_area(x, y, count):
    """Shoelace area of (P, S) polygons with ``count`` vertices each."""
    s = x.shape[1]
    nxt = _next_slots(count, s)
    cross = x * torch.gather(y, 1, nxt) - torch.gather(x, 1, nxt) * y
    cross = torch.where(torch.arange(s, device=x.device) < count[:, None], cross, 0.0)
    area = 0.5 * cross.sum(dim=1).abs()
    return torch.where(count >= 3, area, 0.0)


def _pair_overlap(ra: torch.Tensor, rb: torch.Tensor) -> torch.Tensor:
    """Intersection areas of paired rectangles (P, 5) [cx, cy, ex, ey, heading]
    (half extents, heading counter-clockwise), float64."""
    ca, sa = torch.cos(ra[:, 4]), torch.sin(ra[:, 4])
    rel_x, rel_y = rb[:, 0] - ra[:, 0], rb[:, 1] - ra[:, 1]
    # b's centre and orientation in a's frame; a rectangle is symmetric under a
    # half turn, so the relative heading is reduced mod pi (exact for 0 and pi).
    loc_x = ca * rel_x + sa * rel_y
    loc_y = ca * rel_y - sa * rel_x
    dh = rb[:, 4] - ra[:, 4]
    dh = dh - math.pi * torch.round(dh / math.pi)
    cd, sd = torch.cos(dh), torch.sin(dh)
    signs = ra.new_tensor(_CORNER_SIGNS)  # (4, 2)
    ux = signs[None, :, 0] * rb[:, None, 2]
    uy = signs[None, :, 1] * rb[:, None, 3]
    # b's corners, counter-clockwise, in a's frame, where a is [-ex, ex] x [-ey, ey].
    x = loc_x[:, None] + cd[:, None] * ux - sd[:, None] * uy
    y = loc_y[:, None] + sd[:, None] * ux + cd[:, None] * uy
    count = torch.full((len(ra),), 4, dtype=torch.long, device=ra.device)
    ex, ey = ra[:, 2], ra[:, 3]
    x, y, count = _clip_half_plane(x, y, count, 1.0, ex, _CAPACITIES[0])
    x, y, count = _clip_half_plane(x, y, count, -1.0, ex, _CAPACITIES[1])
    y, x, count = _clip_half_plane(y, x, count, 1.0, ey, _CAPACITIES[2])
    y, x, count = _clip_half_plane(y, x, count, -1.0, ey, _CAPACITIES[3])
    return _polygon_area(x, y, count)


def _candidate_pairs(ra: torch.Tensor, rb: torch.Tensor, upper_only: bool = False):
    """Yield (ia, ib) index chunks of the pairs whose circumscribed circles meet
    (all others are disjoint); ``upper_only`` keeps ia < ib (one set against itself)."""
    n, m = len(ra), len(rb)
    if n == 0 or m == 0:
        return
    # Radii with a relative slack of 1e-9, so that rounding never drops a pair.
    rad_a = torch.hypot(ra[:, 2], ra[:, 3]) * (1 + 1e-9) + 1e-12
    rad_b = torch.hypot(rb[:, 2], rb[:, 3]) * (1 + 1e-9) + 1e-12
    kind = ra.device.type
    rows = max(1, _PREFILTER_CHUNK.get(kind, _PREFILTER_CHUNK_DEFAULT) // m)
    step = _PAIR_CHUNK.get(kind, _PAIR_CHUNK_DEFAULT)
    for r0 in range(0, n, rows):
        r1 = min(n, r0 + rows)
        c0 = r0 + 1 if upper_only else 0  # columns left of the block's diagonal never count
        if c0 >= m:
            break
        dist = torch.cdist(ra[r0:r1, :2], rb[c0:, :2], compute_mode="donot_use_mm_for_euclid_dist")
        near = dist <= rad_a[r0:r1, None] + rad_b[None, c0:]
        if upper_only:
            near = torch.triu(near)  # column c0 + j pairs with row r0 + i when j >= i
        ia, ib = torch.nonzero(near, as_tuple=True)
        ia, ib = ia + r0, ib + c0
        for p0 in range(0, len(ia), step):
            yield ia[p0:p0 + step], ib[p0:p0 + step]


def _overlap_matrix(ra: torch.Tensor, rb: torch.Tensor) -> torch.Tensor:
    """(N, M) float64 intersection areas of rectangles (N, 5) x (M, 5) given as
    [cx, cy, ex, ey, heading] float64 (half extents, counter-clockwise)."""
    out = ra.new_zeros(len(ra), len(rb))
    for ia, ib in _candidate_pairs(ra, rb):
        out[ia, ib] = _pair_overlap(ra[ia], rb[ib])
    return out


def _bev_rects(boxes: torch.Tensor) -> torch.Tensor:
    """Lidar boxes (N, >=7) -> float64 [cx, cy, ex, ey, heading] (sizes < 0 -> 0)."""
    b = boxes.to(torch.float64)
    half = 0.5 * b[:, 3:5].clamp(min=0)
    return torch.cat([b[:, 0:2], half, b[:, 6:7]], dim=1)


def _bev_overlap64(boxes_a, boxes_b):
    _check_boxes(boxes_a, 7, "boxes_a")
    _check_boxes(boxes_b, 7, "boxes_b")
    return _overlap_matrix(_bev_rects(boxes_a), _bev_rects(boxes_b.to(boxes_a.device)))


def boxes_overlap_bev(boxes_a: torch.Tensor, boxes_b: torch.Tensor) -> torch.Tensor:
    """(N, M) bird's-eye-view intersection areas of lidar boxes (N, 7) x (M, 7)."""
    return _bev_overlap64(boxes_a, boxes_b).to(_result_dtype(boxes_a, boxes_b))


def _areas(boxes: torch.Tensor) -> torch.Tensor:
    b = boxes.to(torch.float64)
    return b[:, 3].clamp(min=0) * b[:, 4].clamp(min=0)


def boxes_iou_bev(boxes_a: torch.Tensor, boxes_b: torch.Tensor) -> torch.Tensor:
    """(N, M) rotated bird's-eye-view IoU of lidar boxes (N, 7) x (M, 7)."""
    inter = _bev_overlap64(boxes_a, boxes_b)
    union = _areas(boxes_a)[:, None] + _areas(boxes_b).to(inter.device)[None, :] - inter
    return (inter / union.clamp(min=_BEV_EPS)).to(_result_dtype(boxes_a, boxes_b))


def _iou_upper_bound(ra: torch.Tensor, rb: torch.Tensor, area_a, area_b) -> torch.Tensor:
    """Cheap upper bound of the IoU of paired rectangles: in each rectangle's own
    frame the intersection is at most its overlap with the other's bounding box
    there, and it is at most either area."""
    def overlap_in_frame_of(r, o):
        c, s = torch.cos(r[:, 4]), torch.sin(r[:, 4])
        rel_x, rel_y = o[:, 0] - r[:, 0], o[:, 1] - r[:, 1]
        loc_x, loc_y = c * rel_x + s * rel_y, c * rel_y - s * rel_x
        cd, sd = torch.cos(o[:, 4] - r[:, 4]).abs(), torch.sin(o[:, 4] - r[:, 4]).abs()
        hx, hy = cd * o[:, 2] + sd * o[:, 3], sd * o[:, 2] + cd * o[:, 3]
        wx = torch.minimum(r[:, 2], loc_x + hx) - torch.maximum(-r[:, 2], loc_x - hx)
        wy = torch.minimum(r[:, 3], loc_y + hy) - torch.maximum(-r[:, 3], loc_y - hy)
        return wx.clamp(min=0) * wy.clamp(min=0)

    inter = torch.minimum(overlap_in_frame_of(ra, rb), overlap_in_frame_of(rb, ra))
    inter = torch.minimum(inter, torch.minimum(area_a, area_b))
    return inter / (area_a + area_b - inter).clamp(min=_BEV_EPS)


def iou_bev_self_pairs(boxes: torch.Tensor, axis_aligned: bool = False, above: float | None = None):
    """Sparse BEV IoU of a box set with itself: (i, j, iou) over the pairs i < j
    that can overlap (float64 IoU), without an (N, N) matrix; for NMS.

    ``axis_aligned`` ignores the headings (dx along x), as OpenPCDet's
    iou_normal. With ``above``, pairs whose IoU provably cannot exceed it (by a
    bounding-box upper bound) are left out before the exact clipping.
    """
    _check_boxes(boxes, 7, "boxes")
    rects, areas = _bev_rects(boxes), _areas(boxes)
    if axis_aligned:
        rects[:, 4] = 0.0
    parts = []
    for ia, ib in _candidate_pairs(rects, rects, True):
        if above is not None:
            # The bound is computed in float64 too; the slack keeps it a bound.
            maybe = _iou_upper_bound(rects[ia], rects[ib], areas[ia], areas[ib]) > above - 1e-9
            ia, ib = ia[maybe], ib[maybe]
        parts.append((ia, ib, _pair_overlap(rects[ia], rects[ib])))
    if not parts:
        empty = torch.zeros(0, dtype=torch.long, device=boxes.device)
        return empty, empty, rects.new_zeros(0)
    ia, ib, inter = (torch.cat(t) for t in zip(*parts))
    union = areas[ia] + areas[ib] - inter
    return ia, ib, inter / union.clamp(min=_BEV_EPS)


def boxes_iou3d(boxes_a: torch.Tensor, boxes_b: torch.Tensor) -> torch.Tensor:
    """(N, M) 3D IoU of lidar boxes (N, 7) x (M, 7): BEV overlap times height overlap."""
    inter_bev = _bev_overlap64(boxes_a, boxes_b)
    a = boxes_a.to(torch.float64)
    b = boxes_b.to(device=a.device, dtype=torch.float64)
    dz_a, dz_b = a[:, 5].clamp(min=0), b[:, 5].clamp(min=0)
    # min(tops) - max(bottoms), written relative to the centres' offset so that
    # identical boxes overlap by exactly dz.
    offset = a[:, 2, None] - b[None, :, 2]
    reach = 0.5 * (dz_a[:, None] + dz_b[None, :])
    overlap_h = torch.minimum(torch.minimum(dz_a[:, None], dz_b[None, :]), reach - offset.abs())
    inter = inter_bev * overlap_h.clamp(min=0)
    vol_a, vol_b = _areas(a) * dz_a, _areas(b) * dz_b
    union = vol_a[:, None] + vol_b[None, :] - inter
    return (inter / union.clamp(min=_VOLUME_EPS)).to(_result_dtype(boxes_a, boxes_b))


def rotated_overlap_2d(rects_a: torch.Tensor, rects_b: torch.Tensor) -> torch.Tensor:
    """(N, M) intersection areas of generic rectangles (N, 5) x (M, 5).

    Rows are [cx, cy, w, l, angle] with ``w`` along the rectangle's own first
    axis and ``angle`` turning it CLOCKWISE in the (cx, cy) plane, as the
    KITTI evaluator's rotate_iou in OpenPCDet (used on camera-frame [x, z, l, w,
    ry] boxes there).
    """
    _check_boxes(rects_a, 5, "rects_a")
    _check_boxes(rects_b, 5, "rects_b")

    def to_rects(r):
        r = r.to(device=rects_a.device, dtype=torch.float64)
        return torch.cat([r[:, 0:2], 0.5 * r[:, 2:4].clamp(min=0), -r[:, 4:5]], dim=1)

    inter = _overlap_matrix(to_rects(rects_a), to_rects(rects_b))
    return inter.to(_result_dtype(rects_a, rects_b))


def boxes_iou_bev_nearest(boxes_a: torch.Tensor, boxes_b: torch.Tensor) -> torch.Tensor:
    """(N, M) axis-aligned BEV IoU after snapping each heading to the nearest of
    0 / 90 degrees (a box within 45 degrees of the y axis swaps dx and dy), as
    OpenPCDet's axis-aligned target assigner (boxes3d_nearest_bev_iou); computed
    in the input dtype like there, union floored at 1e-6."""
    _check_boxes(boxes_a, 7, "boxes_a")
    _check_boxes(boxes_b, 7, "boxes_b")
    boxes_b = boxes_b.to(boxes_a.device)
    dtype = _result_dtype(boxes_a, boxes_b)

    def aligned(boxes):
        b = boxes.to(dtype)
        # |heading| folded into [0, pi/2]: below pi/4 keeps the box's x along x.
        folded = (b[:, 6] - torch.floor(b[:, 6] / math.pi + 0.5) * math.pi).abs()
        dims = torch.where((folded < math.pi / 4)[:, None], b[:, 3:5], b[:, [4, 3]])
        return b[:, 0:2] - 0.5 * dims, b[:, 0:2] + 0.5 * dims

    lo_a, hi_a = aligned(boxes_a)
    lo_b, hi_b = aligned(boxes_b)
    side = (torch.minimum(hi_a[:, None], hi_b[None]) - torch.maximum(lo_a[:, None], lo_b[None])).clamp(min=0)
    inter = side[..., 0] * side[..., 1]
    area_a = (hi_a - lo_a).prod(dim=1)
    area_b = (hi_b - lo_b).prod(dim=1)
    return inter / (area_a[:, None] + area_b[None, :] - inter).clamp(min=1e-6)
