"""Detection box and point operators against brute-force references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from omnilidar.geometry import rotated_iou as iou

try:  # test-only reference geometry (the "test" extra)
    from shapely.geometry import Polygon
except ImportError:  # pragma: no cover - e.g. on a bare GPU machine
    Polygon = None
needs_shapely = pytest.mark.skipif(Polygon is None, reason="shapely (test extra) is not installed")


def _random_boxes(gen: torch.Generator, n: int, spread: float = 3.0) -> torch.Tensor:
    centre = (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) * 2 * spread
    size = 0.2 + 4 * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    heading = (torch.rand(n, 1, generator=gen, dtype=torch.float64) - 0.5) * 4 * math.pi
    return torch.cat([centre, size, heading], dim=1)


def _polygon(cx, cy, ex, ey, ccw_angle):
    c, s = math.cos(ccw_angle), math.sin(ccw_angle)
    pts = [(cx + c * u - s * v, cy + s * u + c * v) for u, v in ((ex, ey), (-ex, ey), (-ex, -ey), (ex, -ey))]
    return Polygon(pts)


def _shapely_overlap_bev(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    pa = [_polygon(x[0], x[1], x[3] / 2, x[4] / 2, x[6]) for x in a.tolist()]
    pb = [_polygon(x[0], x[1], x[3] / 2, x[4] / 2, x[6]) for x in b.tolist()]
    return np.array([[p.intersection(q).area for q in pb] for p in pa]).reshape(len(pa), len(pb))


# ---------------------------------------------------------------- IoU


@needs_shapely
def test_bev_overlap_matches_shapely():
    gen = torch.Generator().manual_seed(0)
    a, b = _random_boxes(gen, 40), _random_boxes(gen, 50)
    got = iou.boxes_overlap_bev(a, b)
    want = _shapely_overlap_bev(a, b)
    assert got.dtype == torch.float64 and (want > 0).mean() > 0.3
    np.testing.assert_allclose(got.numpy(), want, atol=1e-9)
    union = (a[:, 3] * a[:, 4])[:, None] + (b[:, 3] * b[:, 4])[None] - torch.from_numpy(want)
    np.testing.assert_allclose(iou.boxes_iou_bev(a, b).numpy(), want / union.numpy(), atol=1e-9)


@needs_shapely
def test_iou3d_is_bev_overlap_times_height_overlap():
    gen = torch.Generator().manual_seed(1)
    a, b = _random_boxes(gen, 30), _random_boxes(gen, 20)
    inter_bev = _shapely_overlap_bev(a, b)
    an, bn = a.numpy(), b.numpy()
    top = np.minimum(an[:, None, 2] + an[:, None, 5] / 2, bn[None, :, 2] + bn[None, :, 5] / 2)
    bottom = np.maximum(an[:, None, 2] - an[:, None, 5] / 2, bn[None, :, 2] - bn[None, :, 5] / 2)
    inter = inter_bev * np.clip(top - bottom, 0, None)
    vol_a, vol_b = an[:, 3:6].prod(1), bn[:, 3:6].prod(1)
    want = inter / (vol_a[:, None] + vol_b[None] - inter)
    np.testing.assert_allclose(iou.boxes_iou3d(a, b).numpy(), want, atol=1e-9)
    assert (want > 0).any()


@needs_shapely
def test_rotated_overlap_2d_turns_clockwise_like_kitti_eval():
    gen = torch.Generator().manual_seed(2)
    a = torch.cat([torch.rand(25, 2, generator=gen) * 4, 0.5 + 3 * torch.rand(25, 2, generator=gen),
                   (torch.rand(25, 1, generator=gen) - 0.5) * 6], dim=1).double()
    b = a.flip(0) + 0.3
    got = iou.rotated_overlap_2d(a, b)
    # [cx, cy, w, l, angle]: w along the own first axis, angle clockwise.
    pa = [_polygon(r[0], r[1], r[2] / 2, r[3] / 2, -r[4]) for r in a.tolist()]
    pb = [_polygon(r[0], r[1], r[2] / 2, r[3] / 2, -r[4]) for r in b.tolist()]
    want = np.array([[p.intersection(q).area for q in pb] for p in pa])
    np.testing.assert_allclose(got.numpy(), want, atol=1e-9)
    # Clockwise is not counter-clockwise: mirrored angles give other overlaps here.
    mirrored = [_polygon(r[0], r[1], r[2] / 2, r[3] / 2, r[4]) for r in a.tolist()]
    assert not np.allclose(want, [[p.intersection(q).area for q in pb] for p in mirrored], atol=1e-3)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_identical_boxes_have_iou_exactly_one(dtype):
    gen = torch.Generator().manual_seed(3)
    boxes = _random_boxes(gen, 20, spread=50.0).to(dtype)
    for fn in (iou.boxes_iou_bev, iou.boxes_iou3d):
        diag = torch.diagonal(fn(boxes, boxes))
        assert diag.dtype == dtype
        assert torch.equal(diag, torch.ones_like(diag)), fn.__name__


def test_touching_and_disjoint_boxes_have_iou_zero():
    a = torch.tensor([[0.0, 0, 0, 2, 2, 2, 0]])
    b = torch.tensor([[2.0, 0, 0, 2, 2, 2, 0], [0, 2, 0, 2, 2, 2, 0], [0, 0, 2, 2, 2, 2, 0], [5, 5, 0, 1, 1, 1, 0.4]])
    assert torch.equal(iou.boxes_iou_bev(a, b[[0, 1, 3]]), torch.zeros(1, 3))
    assert torch.equal(iou.boxes_iou3d(a, b), torch.zeros(1, 4))


def test_zero_size_boxes_give_zero_not_nan():
    a = torch.tensor([[0.0, 0, 0, 0, 0, 0, 0], [0, 0, 0, 2, 0, 1, 0.3], [0, 0, 0, 2, 2, 2, 0]])
    for fn in (iou.boxes_iou_bev, iou.boxes_iou3d, iou.boxes_overlap_bev, iou.boxes_iou_bev_nearest):
        out = fn(a, a)
        assert torch.isfinite(out).all(), fn.__name__
        assert torch.equal(out[:2], torch.zeros(2, 3)) and torch.equal(out[:, :2], torch.zeros(3, 2)), fn.__name__


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_half_turns_and_quarter_turned_squares_are_the_same_rectangle(dtype):
    box = torch.tensor([[1.0, -2.0, 0.5, 4.0, 1.5, 1.6, 0.0]], dtype=dtype)
    turned = box.repeat(3, 1)
    turned[:, 6] = torch.tensor([math.pi, -math.pi, 3 * math.pi], dtype=dtype)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(iou.boxes_iou_bev(box, turned), torch.ones(1, 3, dtype=dtype), atol=tol, rtol=0)
    torch.testing.assert_close(iou.boxes_iou_bev(turned, turned), torch.ones(3, 3, dtype=dtype), atol=tol, rtol=0)
    square = torch.tensor([[3.0, 3.0, 0.0, 2.0, 2.0, 2.0, 0.0], [3.0, 3.0, 0.0, 2.0, 2.0, 2.0, math.pi / 2]], dtype=dtype)
    torch.testing.assert_close(iou.boxes_iou3d(square, square), torch.ones(2, 2, dtype=dtype), atol=tol, rtol=0)


@needs_shapely
def test_nearly_parallel_boxes_far_from_origin_match_the_same_pair_at_origin():
    near = torch.tensor([[0.0, 0.0, 0.0, 4.2, 1.8, 1.5, 0.0], [0.05, 0.02, 0.0, 4.2, 1.8, 1.5, 1e-5],
                         [0.0, 1.8, 0.0, 4.2, 1.8, 1.5, 0.0]], dtype=torch.float64)
    far = near.clone()
    far[:, 0] += 1e4
    far[:, 1] -= 1e4
    want = iou.boxes_iou_bev(near, near)
    inter = torch.from_numpy(_shapely_overlap_bev(near, near))
    area = near[:, 3] * near[:, 4]
    torch.testing.assert_close(want, inter / (area[:, None] + area[None] - inter), atol=1e-9, rtol=0)
    torch.testing.assert_close(iou.boxes_iou_bev(far, far), want, atol=1e-9, rtol=0)
    assert 0.9 < want[0, 1] < 1.0 and want[0, 2] == 0 and want[2, 0] == 0  # shared edge -> 0
    # The same far pair in float32 (centres rounded to float32) stays sane.
    got32 = iou.boxes_iou_bev(far.float(), far.float())
    assert torch.isfinite(got32).all() and (got32 >= 0).all() and (got32 <= 1).all()
    torch.testing.assert_close(got32.double(), want, atol=5e-3, rtol=0)


def test_coincident_edges_and_corner_touching_are_exact():
    a = torch.tensor([[0.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.0]], dtype=torch.float64)
    b = torch.tensor([[1.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.0],   # half overlap, two shared edges
                      [1.0, 1.0, 0.0, 2.0, 2.0, 1.0, 0.0],   # quarter overlap
                      [2.0, 2.0, 0.0, 2.0, 2.0, 1.0, 0.0],   # corner touching
                      [0.0, 0.0, 0.0, 2.0, 1.0, 1.0, 0.0]],  # inside, sharing two edges
                     dtype=torch.float64)
    torch.testing.assert_close(iou.boxes_overlap_bev(a, b), torch.tensor([[2.0, 1.0, 0.0, 2.0]], dtype=torch.float64),
                               atol=1e-12, rtol=0)


def test_empty_inputs_give_empty_matrices():
    boxes = torch.zeros(3, 7)
    empty = torch.zeros(0, 7)
    for fn in (iou.boxes_iou_bev, iou.boxes_iou3d, iou.boxes_overlap_bev, iou.boxes_iou_bev_nearest):
        assert fn(empty, boxes).shape == (0, 3) and fn(boxes, empty).shape == (3, 0)
    assert iou.rotated_overlap_2d(torch.zeros(0, 5), torch.zeros(2, 5)).shape == (0, 2)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match=r"boxes_b must be an \(N, 7\)"):
        iou.boxes_iou_bev(torch.zeros(2, 7), torch.zeros(2, 5))
    with pytest.raises(ValueError, match="floating point"):
        iou.boxes_iou3d(torch.zeros(2, 7, dtype=torch.long), torch.zeros(2, 7))


def test_nearest_bev_iou_snaps_headings_to_the_axes():
    a = torch.tensor([[0.0, 0, 0, 4, 2, 1, 0.2], [0.0, 0, 0, 4, 2, 1, math.pi / 2 - 0.3],
                      [0.0, 0, 0, 4, 2, 1, -math.pi + 0.1]])
    b = torch.tensor([[0.0, 0, 0, 4, 2, 1, 0.0], [1.0, 0, 0, 2, 4, 1, 0.0]])
    got = iou.boxes_iou_bev_nearest(a, b)
    # a0 and a2 snap to 0 deg (4 x 2 along x), a1 to 90 deg (2 x 4); every
    # non-identical pair overlaps by 4 m^2 of a 12 m^2 union.
    want = torch.tensor([[1.0, 1 / 3], [1 / 3, 1 / 3], [1.0, 1 / 3]])
    torch.testing.assert_close(got, want)


_finite = dict(allow_nan=False, allow_infinity=False)
_box = st.tuples(
    st.floats(-5, 5, **_finite), st.floats(-5, 5, **_finite), st.floats(-2, 2, **_finite),
    st.floats(0.05, 6, **_finite), st.floats(0.05, 6, **_finite), st.floats(0.05, 4, **_finite),
    st.floats(-4, 4, **_finite),
)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.lists(_box, min_size=1, max_size=6), st.lists(_box, min_size=1, max_size=6))
def test_iou_properties(rows_a, rows_b):
    a = torch.tensor(rows_a, dtype=torch.float64)
    b = torch.tensor(rows_b, dtype=torch.float64)
    ab, ba = iou.boxes_iou_bev(a, b), iou.boxes_iou_bev(b, a)
    assert ((ab >= 0) & (ab <= 1 + 1e-12)).all()
    torch.testing.assert_close(ab, ba.T, atol=1e-10, rtol=0)
    torch.testing.assert_close(torch.diagonal(iou.boxes_iou_bev(a, a)), torch.ones(len(a), dtype=a.dtype),
                               atol=1e-12, rtol=0)
    d3 = iou.boxes_iou3d(a, b)
    assert ((d3 >= 0) & (d3 <= 1 + 1e-12)).all()
    torch.testing.assert_close(d3, iou.boxes_iou3d(b, a).T, atol=1e-10, rtol=0)
    # With one height interval inside the other, 3D IoU cannot exceed BEV IoU.
    b_tall = b.clone()
    b_tall[:, 2], b_tall[:, 5] = 0.0, 100.0
    assert (iou.boxes_iou3d(a, b_tall) <= iou.boxes_iou_bev(a, b_tall) + 1e-12).all()



_near = st.floats(-1e-3, 1e-3, allow_nan=False, allow_infinity=False)


@settings(max_examples=80, deadline=None, derandomize=True)
@given(st.floats(-math.pi, math.pi, **_finite), st.floats(0.3, 5, **_finite), st.floats(0.3, 3, **_finite),
       st.sampled_from([0.0, 0.5, 1.0, 2.0]), st.sampled_from([0.0, 1.0]), _near, _near, _near)
def test_nearly_parallel_and_edge_sharing_pairs_are_shift_invariant(heading, dx, dy, along, across, eps_h, eps_x, eps_y):
    """b is a slid along its own axes by a fraction of its size (shared edges at
    1.0), nudged by up to 1e-3; the IoU must not depend on where the pair sits."""
    c, s_ = math.cos(heading), math.sin(heading)
    sx, sy = along * dx + eps_x, across * dy + eps_y
    a = [0.0, 0.0, 0.0, dx, dy, 1.0, heading]
    b = [c * sx - s_ * sy, s_ * sx + c * sy, 0.0, dx, dy, 1.0, heading + eps_h]
    near = torch.tensor([a, b], dtype=torch.float64)
    far = near.clone()
    far[:, 0] += 1e4
    far[:, 1] -= 3e4
    want = iou.boxes_iou_bev(near, near)
    got = iou.boxes_iou_bev(far, far)
    assert torch.isfinite(got).all() and ((got >= 0) & (got <= 1 + 1e-12)).all()
    torch.testing.assert_close(got, want, atol=1e-9, rtol=0)
    torch.testing.assert_close(torch.diagonal(got), torch.ones(2, dtype=torch.float64), atol=1e-12, rtol=0)
    if Polygon is not None:
        inter = _shapely_overlap_bev(near, near)[0, 1]
        assert abs(float(iou.boxes_overlap_bev(near, near)[0, 1]) - inter) < 1e-9


def test_chunked_evaluation_gives_the_same_answers(monkeypatch):
    gen = torch.Generator().manual_seed(11)
    a, b = _random_boxes(gen, 70, 5.0), _random_boxes(gen, 50, 5.0)
    whole = iou.boxes_iou_bev(a, b)
    ia, ib, pairs = iou.iou_bev_self_pairs(a)
    monkeypatch.setattr(iou, "_PREFILTER_CHUNK", {"cpu": 7 * 50})  # 7 rows per block, ragged end
    monkeypatch.setattr(iou, "_PAIR_CHUNK", {"cpu": 13})
    assert torch.equal(iou.boxes_iou_bev(a, b), whole)
    ja, jb, chunked = iou.iou_bev_self_pairs(a)
    assert (ja < jb).all() and len(set(zip(ja.tolist(), jb.tolist()))) == len(ja)
    dense = iou.boxes_iou_bev(a, a)
    torch.testing.assert_close(chunked, dense[ja, jb], atol=1e-12, rtol=0)
    # Every overlapping pair i < j is listed, chunked or not.
    assert sorted(zip(ja.tolist(), jb.tolist())) == sorted(zip(ia.tolist(), ib.tolist()))
    assert {(i, j) for i, j in (torch.triu(dense, 1) > 0).nonzero().tolist()} <= set(zip(ja.tolist(), jb.tolist()))


# ---------------------------------------------------------------- NMS

from omnilidar.downstream.det.ops import nms  # noqa: E402


def _brute_force_nms(boxes, scores, thresh, pre=None, post=None, aligned=False):
    order = sorted(range(len(scores)), key=lambda i: (-float(scores[i]), i))[:pre]
    b = boxes.clone()
    if aligned:
        b[:, 6] = 0
    ious = iou.boxes_iou_bev(b, b).tolist()
    keep = []
    for i in order:
        if all(ious[i][j] <= thresh for j in keep):
            keep.append(i)
    return keep[:post]


@pytest.mark.parametrize("aligned", [False, True])
def test_nms_matches_brute_force_greedy(aligned):
    gen = torch.Generator().manual_seed(4)
    boxes = _random_boxes(gen, 120, spread=6.0).float()
    scores = torch.rand(120, generator=gen)
    scores[10] = scores[11]  # a tie: the lower index goes first
    for thresh, pre, post in ((0.1, None, None), (0.5, 80, None), (0.3, None, 7), (0.0, 50, 20)):
        got = nms.nms_rotated(boxes, scores, thresh, pre, post, axis_aligned=aligned)
        assert got.dtype == torch.long
        assert got.tolist() == _brute_force_nms(boxes, scores, thresh, pre, post, aligned)
    assert 0 < len(nms.nms_rotated(boxes, scores, 0.1)) < 120  # suppression happened
    assert nms.nms_rotated(boxes[:0], scores[:0], 0.5).shape == (0,)


def test_nms_suppresses_only_above_threshold():
    boxes = torch.tensor([[0.0, 0, 0, 2, 2, 1, 0], [1.0, 0, 0, 2, 2, 1, 0], [0.0, 0, 0, 2, 2, 1, math.pi]])
    scores = torch.tensor([0.9, 0.8, 0.7])
    # IoU(0, 1) = 1/3; box 2 is box 0 turned half a turn (IoU 1).
    assert nms.nms_rotated(boxes, scores, 1 / 3 + 1e-6).tolist() == [0, 1]
    assert nms.nms_rotated(boxes, scores, 0.3).tolist() == [0]


def test_class_agnostic_and_multi_class_nms_follow_openpcdet():
    cfg = {"NMS_TYPE": "nms_gpu", "NMS_THRESH": 0.1, "NMS_PRE_MAXSIZE": 4, "NMS_POST_MAXSIZE": 2}
    boxes = torch.tensor([[0.0, 0, 0, 2, 2, 1, 0], [0.2, 0, 0, 2, 2, 1, 0], [5.0, 0, 0, 2, 2, 1, 0],
                          [10.0, 0, 0, 2, 2, 1, 0], [20.0, 0, 0, 2, 2, 1, 0]])
    scores = torch.tensor([0.5, 0.9, 0.05, 0.6, 0.7])
    sel, sel_scores = nms.class_agnostic_nms(scores, boxes, cfg, score_thresh=0.1)
    assert sel.tolist() == [1, 4] and torch.equal(sel_scores, scores[[1, 4]])
    cls = torch.stack([scores, 1 - scores], dim=1)
    s, labels, b = nms.multi_class_nms(cls, boxes, dict(cfg, NMS_POST_MAXSIZE=10), score_thresh=0.35)
    assert labels.tolist() == [0, 0, 0, 1, 1, 1]
    torch.testing.assert_close(s, torch.tensor([0.9, 0.7, 0.6, 0.95, 0.5, 0.4]))
    assert torch.equal(b, boxes[[1, 4, 3, 2, 0, 3]])
    with pytest.raises(ValueError, match="NMS_TYPE 'soft'"):
        nms.class_agnostic_nms(scores, boxes, dict(cfg, NMS_TYPE="soft"))


# ---------------------------------------------------------------- points in boxes

from omnilidar.geometry import points_in_boxes as det_points  # noqa: E402
from omnilidar.geometry.boxes import box_corners  # noqa: E402


def test_points_in_boxes_match_a_per_pair_loop():
    gen = torch.Generator().manual_seed(5)
    boxes = _random_boxes(gen, 12, spread=4.0).float()
    pts = (torch.rand(3000, 4, generator=gen) - 0.5) * 10
    mask = det_points.points_in_boxes_mask(pts, boxes)
    want = torch.zeros(3000, 12, dtype=torch.bool)
    for j, (cx, cy, cz, dx, dy, dz, h) in enumerate(boxes.double().tolist()):
        for i, (x, y, z) in enumerate(pts[:, :3].double().tolist()):
            u = (x - cx) * math.cos(h) + (y - cy) * math.sin(h)
            v = -(x - cx) * math.sin(h) + (y - cy) * math.cos(h)
            want[i, j] = abs(u) <= dx / 2 and abs(v) <= dy / 2 and abs(z - cz) <= dz / 2
    assert torch.equal(mask, want) and want.any(dim=1).float().mean() > 0.05
    first = det_points.points_in_boxes(pts, boxes)
    expected = torch.where(want.any(1), want.int().argmax(1), -1)  # argmax: first True
    assert first.dtype == torch.long and torch.equal(first, expected)
    assert (want.sum(1) > 1).any()  # overlapping boxes exercised the lowest-index rule


def test_points_on_faces_count_and_empty_inputs():
    box = torch.tensor([[1.0, 2.0, 0.5, 2.0, 4.0, 1.0, math.pi / 2]])
    # Rotated by 90 deg: x extent 4 (dy), y extent 2 (dx).
    pts = torch.tensor([[3.0, 2.0, 0.5], [1.0, 3.0, 1.0], [1.0, 2.0, 0.0], [3.01, 2.0, 0.5], [1.0, 2.0, 1.01]],
                       dtype=torch.float64)
    assert det_points.points_in_boxes_mask(pts, box)[:, 0].tolist() == [True, True, True, False, False]
    assert det_points.points_in_boxes(pts, box).tolist() == [0, 0, 0, -1, -1]
    assert det_points.points_in_boxes_mask(pts[:0], box).shape == (0, 1)
    assert det_points.points_in_boxes(pts, box[:0]).tolist() == [-1] * 5
    with pytest.raises(ValueError, match="boxes must be"):
        det_points.points_in_boxes(pts, box[:, :6])


def _dense_inside(pts: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """All pairs, with torch's cos / sin (numpy's may differ by an ulp, which
    matters for points exactly on a face)."""
    p, b = torch.from_numpy(pts), torch.from_numpy(boxes)
    ox, oy = p[:, None, 0] - b[None, :, 0], p[:, None, 1] - b[None, :, 1]
    c, s_ = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    return (((ox * c + oy * s_).abs() <= 0.5 * b[:, 3]) & ((oy * c - ox * s_).abs() <= 0.5 * b[:, 4])
            & ((p[:, None, 2] - b[None, :, 2]).abs() <= 0.5 * b[:, 5])).numpy()


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.0, 1e4, -3e4]), st.integers(1, 60), st.floats(0.0, 1.0))
def test_points_in_boxes_never_miss_a_point(seed, offset, n_boxes, zero_fraction):
    """Sorted-strip candidate search against a dense float64 test, with points on
    faces and corners, zero-size boxes, boxes away from every point, far offsets."""
    rng = np.random.default_rng(seed)
    boxes = np.column_stack([rng.uniform(-12, 12, (n_boxes, 3)), rng.uniform(0.1, 6, (n_boxes, 3)),
                             rng.uniform(-4, 4, n_boxes)])
    boxes[rng.random(n_boxes) < zero_fraction * 0.3, 3:6] = 0.0
    boxes[rng.random(n_boxes) < 0.1, 0] += 100.0  # far from all points
    corners = np.concatenate([box_corners(boxes[:, :7]).reshape(-1, 3), boxes[:, :3]])
    pts = np.concatenate([rng.uniform(-15, 15, (400, 3)), corners])
    pts[:, :2] += offset
    boxes[:, :2] += offset
    got = det_points.points_in_boxes_mask(torch.from_numpy(pts), torch.from_numpy(boxes)).numpy()
    np.testing.assert_array_equal(got, _dense_inside(pts, boxes))


# ---------------------------------------------------------------- sampling and grouping

from omnilidar.downstream.det.ops import sampling  # noqa: E402


def test_farthest_point_sample_matches_a_brute_force_loop():
    gen = torch.Generator().manual_seed(6)
    xyz = torch.rand(2, 300, 3, generator=gen) * 10
    xyz[1, 7] = xyz[1, 3]  # duplicate points
    got = sampling.farthest_point_sample(xyz, 40)
    for b in range(2):
        chosen, nearest = [0], [float("inf")] * 300
        pts = xyz[b].tolist()
        for _ in range(39):
            last = pts[chosen[-1]]
            for k, p in enumerate(pts):
                nearest[k] = min(nearest[k], sum((p[i] - last[i]) ** 2 for i in range(3)))
            chosen.append(max(range(300), key=lambda k: (nearest[k], -k)))
        assert got[b].tolist() == chosen
    assert got.dtype == torch.long and len(set(got[0].tolist())) == 40
    # More samples than points: every point once, then index 0 again.
    few = sampling.farthest_point_sample(xyz[:, :5], 8)
    assert sorted(few[0, :5].tolist()) == [0, 1, 2, 3, 4] and few[0, 5:].tolist() == [0, 0, 0]


def test_ball_query_takes_the_first_points_in_index_order_pads_and_flags_empty_balls():
    xyz = torch.tensor([[5.0, 0, 0], [0.5, 0, 0], [0, 0, 0], [0.9, 0, 0], [1.0, 0, 0], [0.2, 0, 0],  # sample 0
                        [0.1, 0, 0], [9.0, 0, 0]])  # sample 1
    new_xyz = torch.tensor([[0.0, 0, 0], [0.0, 0, 0.99], [20.0, 0, 0], [0.0, 0, 0]])
    idx, empty = sampling.ball_query(1.0, 3, xyz, torch.tensor([6, 2]), new_xyz, torch.tensor([3, 1]))
    # Centre 0: points 1, 2, 3, 5 lie within (point 4 at distance exactly 1 does not): first three.
    # Centre 1: only point 2 (distance 0.99): padded with it. Centre 2: empty.
    # Centre 3 (sample 1): local point 0.
    assert idx.tolist() == [[1, 2, 3], [2, 2, 2], [0, 0, 0], [0, 0, 0]]
    assert empty.tolist() == [False, False, True, False]


def test_ball_query_matches_a_brute_force_loop():
    gen = torch.Generator().manual_seed(7)
    xyz = torch.rand(250, 3, generator=gen) * 4
    new_xyz = torch.rand(60, 3, generator=gen) * 5
    xyz_cnt, new_cnt = torch.tensor([100, 0, 150]), torch.tensor([20, 15, 25])
    idx, empty = sampling.ball_query(0.6, 5, xyz, xyz_cnt, new_xyz, new_cnt)
    starts, centre_batch = [0, 100, 100], [0] * 20 + [1] * 15 + [2] * 25
    for m, b in enumerate(centre_batch):
        pts = xyz[starts[b]:starts[b] + int(xyz_cnt[b])]
        hits = [k for k in range(len(pts)) if float(((pts[k] - new_xyz[m]) ** 2).sum()) < 0.36][:5]
        want = (hits + [hits[0]] * 5)[:5] if hits else [0] * 5
        assert idx[m].tolist() == want and bool(empty[m]) == (not hits)
    assert empty[20:35].all() and (~empty).sum() > 10 and (idx[~empty][:, 0] != idx[~empty][:, -1]).any()


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.0, 500.0, -4e3]), st.sampled_from([0.3, 1.0, 2.5]),
       st.integers(1, 40), st.lists(st.integers(0, 120), min_size=1, max_size=3))
def test_ball_query_matches_a_dense_reference(seed, offset, radius, nsample, counts):
    """Strip-search ball query against all pairs, with points exactly at the radius,
    duplicates and samples without points."""
    rng = np.random.default_rng(seed)
    n = sum(counts)
    pts = rng.uniform(-4, 4, (n, 3)).astype(np.float32)
    centres_per = [int(rng.integers(0, 30)) for _ in counts]
    ctr = rng.uniform(-4, 4, (sum(centres_per), 3)).astype(np.float32)
    if n > 3:
        pts[1] = pts[0]  # duplicate point
        pts[2] = pts[0] + np.float32([radius, 0, 0])  # exactly on a radius (of a centre at pts[0])
    if len(ctr):
        ctr[0] = pts[0] if n and counts[0] else ctr[0]
    pts[:, :2] += offset
    ctr[:, :2] += offset
    xyz, new_xyz = torch.from_numpy(pts), torch.from_numpy(ctr)
    idx, empty = sampling.ball_query(radius, nsample, xyz, torch.tensor(counts), new_xyz, torch.tensor(centres_per))
    r2 = float(torch.tensor(radius, dtype=torch.float32) ** 2)
    p0 = c0 = 0
    for cnt, ccnt in zip(counts, centres_per):
        block, centres = xyz[p0:p0 + cnt], new_xyz[c0:c0 + ccnt]
        d2 = ((centres[:, None, 0] - block[None, :, 0]) ** 2 + (centres[:, None, 1] - block[None, :, 1]) ** 2
              + (centres[:, None, 2] - block[None, :, 2]) ** 2)
        for m, row in enumerate((d2 < r2).tolist()):
            hits = [k for k, h in enumerate(row) if h][:nsample]
            want = (hits + [hits[0]] * nsample)[:nsample] if hits else [0] * nsample
            assert idx[c0 + m].tolist() == want and bool(empty[c0 + m]) == (not hits)
        p0, c0 = p0 + cnt, c0 + ccnt


def test_grouping_and_query_and_group():
    gen = torch.Generator().manual_seed(8)
    xyz = torch.rand(30, 3, generator=gen)
    feats = torch.rand(30, 4, generator=gen, requires_grad=True)
    xyz_cnt, new_cnt = torch.tensor([10, 20]), torch.tensor([2, 3])
    idx = torch.tensor([[0, 1], [9, 9], [0, 19], [5, 5], [3, 0]])
    out = sampling.grouping_operation(feats, xyz_cnt, idx, new_cnt)
    assert out.shape == (5, 4, 2)
    assert torch.equal(out[2, :, 1], feats[10 + 19]) and torch.equal(out[1, :, 0], feats[9])
    out.sum().backward()
    assert feats.grad[9].tolist() == [2.0] * 4 and feats.grad[15].tolist() == [2.0] * 4
    new_xyz = torch.cat([xyz[[0, 1]], torch.full((1, 3), 50.0), xyz[[12, 13]]])
    grouped, gidx, empty = sampling.query_and_group(0.3, 4, xyz, xyz_cnt, new_xyz, new_cnt, feats.detach())
    assert grouped.shape == (5, 7, 4) and empty.tolist() == [False, False, True, False, False]
    assert torch.equal(grouped[2], torch.zeros(7, 4))
    want_idx, _ = sampling.ball_query(0.3, 4, xyz, xyz_cnt, new_xyz, new_cnt)
    assert torch.equal(gidx, want_idx)
    torch.testing.assert_close(grouped[3, :3, 0], xyz[10 + gidx[3, 0]] - new_xyz[3])
    torch.testing.assert_close(grouped[3, 3:, 1], feats.detach()[10 + gidx[3, 1]])
    module_out, module_idx = sampling.QueryAndGroup(0.3, 4)(xyz, xyz_cnt, new_xyz, new_cnt, feats.detach())
    assert torch.equal(module_out, grouped) and torch.equal(module_idx, gidx)


def _brute_force_voxel_query(max_range, radius, nsample, xyz, new_xyz, new_coords, point_indices):
    _, nz, ny, nx = point_indices.shape
    rows, empties = [], []
    for m in range(len(new_xyz)):
        b, cz, cy, cx = new_coords[m].tolist()
        found = []
        for dz in range(-max_range[0], max_range[0] + 1):
            for dy in range(-max_range[1], max_range[1] + 1):
                for dx in range(-max_range[2], max_range[2] + 1):
                    z, y, x = cz + dz, cy + dy, cx + dx
                    if not (0 <= z < nz and 0 <= y < ny and 0 <= x < nx):
                        continue
                    k = int(point_indices[b, z, y, x])
                    if k >= 0 and float(((xyz[k] - new_xyz[m]) ** 2).sum()) <= radius ** 2:
                        found.append(k)
        empties.append(not found)
        rows.append((found[:nsample] + [found[0]] * nsample)[:nsample] if found else [0] * nsample)
    return rows, empties


def test_voxel_query_matches_the_scan_order_of_voxel_rcnn():
    gen = torch.Generator().manual_seed(9)
    nz, ny, nx, voxel = 3, 8, 8, 0.5
    occupied = torch.rand(2, nz, ny, nx, generator=gen) < 0.4
    occupied[0, :, :3, :3] = False  # the window around voxel (0, 1, 0, 0) is empty
    coords = occupied.nonzero()  # (P, 4) b z y x; its row order makes point indices global
    xyz = (coords[:, [3, 2, 1]].float() + torch.rand(len(coords), 3, generator=gen)) * voxel
    point_indices = torch.full((2, nz, ny, nx), -1, dtype=torch.int32)
    point_indices[occupied] = torch.arange(len(coords), dtype=torch.int32)
    new_coords = torch.cat([torch.randint(0, 2, (40, 1), generator=gen), torch.randint(0, nz, (40, 1), generator=gen),
                            torch.randint(0, ny, (40, 2), generator=gen)], dim=1)
    new_coords = torch.cat([torch.tensor([[0, 1, 0, 0]]), new_coords])
    new_coords = new_coords[new_coords[:, 0].argsort(stable=True)]
    new_xyz = (new_coords[:, [3, 2, 1]].float() + 0.5) * voxel
    idx, empty = sampling.voxel_query((1, 2, 2), 0.8, 6, xyz, new_xyz, new_coords, point_indices)
    want, want_empty = _brute_force_voxel_query((1, 2, 2), 0.8, 6, xyz, new_xyz, new_coords, point_indices)
    assert idx.tolist() == want and empty.tolist() == want_empty
    assert any(want_empty) and not all(want_empty)
    assert any(len(set(row)) == 6 for row in want)  # more than nsample hits: truncated in scan order
    # The grouping module turns global indices into sample-local ones.
    xyz_cnt = torch.bincount(coords[:, 0], minlength=2)
    new_cnt = torch.bincount(new_coords[:, 0], minlength=2)
    feats = torch.rand(len(coords), 5, generator=gen)
    grouper = sampling.VoxelQueryAndGrouping((1, 2, 2), 0.8, 6)
    g_feats, g_xyz, g_empty = grouper(new_coords, xyz, xyz_cnt, new_xyz, new_cnt, feats, point_indices)
    assert torch.equal(g_empty, empty)
    start = (torch.cumsum(xyz_cnt, 0) - xyz_cnt)[new_coords[:, 0]][:, None]
    flat = torch.where(empty[:, None], start, idx)  # empty balls group local point 0
    assert torch.equal(g_feats, feats[flat].permute(0, 2, 1))
    assert torch.equal(g_xyz, xyz[flat].permute(0, 2, 1))




def test_voxel_query_with_shared_centre_voxels_edges_and_small_chunks(monkeypatch):
    # RoI grid points: many centres in one voxel at different positions, windows cut by
    # the grid's edges, a non-cubic window, and chunks far smaller than the work.
    gen = torch.Generator().manual_seed(21)
    nz, ny, nx, voxel = 4, 12, 10, 0.4
    occupied = torch.rand(2, nz, ny, nx, generator=gen) < 0.25
    coords = occupied.nonzero()
    xyz = (coords[:, [3, 2, 1]].float() + torch.rand(len(coords), 3, generator=gen)) * voxel
    point_indices = torch.full((2, nz, ny, nx), -1, dtype=torch.int32)
    point_indices[occupied] = torch.arange(len(coords), dtype=torch.int32)
    centres = torch.rand(300, 3, generator=gen) * torch.tensor([nx * 0.5, ny * 0.5, nz]) * voxel
    new_xyz = torch.cat([centres, centres[:60] + 0.01])
    batch = torch.cat([torch.zeros(150), torch.ones(150), torch.zeros(60)]).long()
    order = batch.argsort(stable=True)
    new_xyz, batch = new_xyz[order], batch[order]
    cell = (new_xyz / voxel).floor().long()
    new_coords = torch.cat([batch[:, None], cell[:, [2, 1, 0]]], 1)
    assert len(torch.unique(new_coords, dim=0)) < len(new_coords) // 2
    want, want_empty = _brute_force_voxel_query((1, 3, 2), 0.7, 5, xyz, new_xyz, new_coords, point_indices)
    for chunk in (1 << 20, 50, 1):
        monkeypatch.setitem(sampling._CHUNK, "cpu", chunk)
        for voxel_map in (point_indices, sampling.VoxelMap.from_coords(coords, point_indices.shape)):
            idx, empty = sampling.voxel_query((1, 3, 2), 0.7, 5, xyz, new_xyz, new_coords, voxel_map)
            assert idx.tolist() == want and empty.tolist() == want_empty
    assert any(want_empty) and not all(want_empty)
    assert any(len(set(row)) == 5 for row in want)
    none = sampling.voxel_query((1, 1, 1), 0.7, 5, xyz, new_xyz[:0], new_coords[:0], point_indices)
    assert none[0].shape == (0, 5) and none[1].shape == (0,)


# ---------------------------------------------------------------- devices


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_every_operator_gives_the_same_answer_on_cuda():
    gen = torch.Generator().manual_seed(10)
    a, b = _random_boxes(gen, 200, 8.0).float(), _random_boxes(gen, 150, 8.0).float()
    cuda = torch.device("cuda")
    for fn in (iou.boxes_iou_bev, iou.boxes_iou3d, iou.boxes_overlap_bev, iou.boxes_iou_bev_nearest):
        got = fn(a.to(cuda), b.to(cuda))
        assert got.device.type == "cuda"
        torch.testing.assert_close(got.cpu(), fn(a, b), atol=1e-6, rtol=0)
    rects = a[:, [0, 1, 3, 4, 6]]
    torch.testing.assert_close(iou.rotated_overlap_2d(rects.to(cuda), rects.to(cuda)).cpu(),
                               iou.rotated_overlap_2d(rects, rects), atol=1e-5, rtol=0)
    scores = torch.rand(200, generator=gen)
    assert torch.equal(nms.nms_rotated(a.to(cuda), scores.to(cuda), 0.2, 150, 60).cpu(),
                       nms.nms_rotated(a, scores, 0.2, 150, 60))
    pts = (torch.rand(5000, 3, generator=gen) - 0.5) * 16
    assert torch.equal(det_points.points_in_boxes(pts.to(cuda), a.to(cuda)).cpu(), det_points.points_in_boxes(pts, a))
    xyz = torch.rand(2, 700, 3, generator=gen) * 10
    assert torch.equal(sampling.farthest_point_sample(xyz.to(cuda), 64).cpu(), sampling.farthest_point_sample(xyz, 64))
    flat, cnt, centres, ccnt = xyz.reshape(-1, 3), torch.tensor([700, 700]), xyz[:, :50].reshape(-1, 3), torch.tensor([50, 50])
    want = sampling.query_and_group(0.8, 16, flat, cnt, centres, ccnt, flat * 2)
    got = sampling.query_and_group(0.8, 16, flat.to(cuda), cnt.to(cuda), centres.to(cuda), ccnt.to(cuda), flat.to(cuda) * 2)
    for g, w in zip(got, want):
        torch.testing.assert_close(g.cpu(), w)
    occupied = torch.rand(1, 4, 10, 10, generator=gen) < 0.3
    coords = occupied.nonzero()
    vox_xyz = coords[:, [3, 2, 1]].float() * 0.4 + 0.2
    point_indices = torch.full((1, 4, 10, 10), -1, dtype=torch.int32)
    point_indices[occupied] = torch.arange(len(coords), dtype=torch.int32)
    args = ((1, 2, 2), 0.9, 8, vox_xyz, vox_xyz[:30], coords[:30], point_indices)
    want = sampling.voxel_query(*args)
    got = sampling.voxel_query(*(a.to(cuda) if torch.is_tensor(a) else a for a in args))
    for g, w in zip(got, want):
        assert torch.equal(g.cpu(), w)
