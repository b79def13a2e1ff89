"""Numerical edge cases and property tests of the range-image projection."""

import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from omnilidar.data.range_image import RangeImageSpec, decode, encode, pixel_angles, project, unproject

SPEC = RangeImageSpec(64, 1024, 3.0, -25.0, 1.45, 80.0)
SMALL = RangeImageSpec(16, 64, 10.0, -20.0, 1.0, 50.0)


def _no_warnings(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return fn(*args, **kwargs)


def _check_clean(proj, n):
    assert proj.point_row.shape == (n,) and proj.point_col.shape == (n,) and proj.valid.shape == (n,)
    assert np.isfinite(proj.range_img).all() and np.isfinite(proj.intensity_img).all()
    assert proj.point_row.dtype == np.int32 and proj.point_index_img.dtype == np.int64


def test_empty_and_single_point():
    proj = _no_warnings(project, np.zeros((0, 4), np.float32), SPEC)
    _check_clean(proj, 0)
    assert not proj.mask.any()
    one = _no_warnings(project, np.array([[10.0, 1.0, -1.0, 0.3]], np.float32), SPEC)
    assert one.mask.sum() == 1 and one.winner.tolist() == [True]


def test_origin_point_is_invalid_but_mapped():
    proj = _no_warnings(project, np.zeros((3, 4), np.float32), SPEC)
    _check_clean(proj, 3)
    assert not proj.valid.any() and not proj.mask.any()
    assert ((proj.point_row >= 0) & (proj.point_row < 64)).all()
    assert ((proj.point_col >= 0) & (proj.point_col < 1024)).all()


def test_azimuth_seam_both_signs_map_to_valid_edge_columns():
    # atan2(+0, -x) = +pi -> column 0; atan2(-0, -x) = -pi -> column W-1
    pts = np.array([[-10.0, 0.0, 0.0, 0.1], [-10.0, -0.0, 0.0, 0.1]], np.float32)
    proj = _no_warnings(project, pts, SPEC)
    assert proj.point_col.tolist() == [0, 1023]
    assert proj.valid.all() and proj.mask.sum() == 2


def test_vertical_points_and_out_of_fov_clip_to_edge_rows():
    # straight up / down (|z/r| = 1 exactly; rounding cannot push asin out of domain
    # since elevation uses atan2) and far outside the vertical field of view
    pts = np.array([[0, 0, 10, 0], [0, 0, -10, 0], [1e-30, 0, 5, 0], [10, 0, 20, 0], [10, 0, -20, 0]], np.float32)
    proj = _no_warnings(project, pts, SPEC)
    assert proj.point_row.tolist() == [0, 63, 0, 0, 63]
    assert proj.valid.all()


def test_range_limits_are_exclusive():
    lo, hi = np.float32(1.45), np.float32(80.0)
    r = np.array([lo, np.nextafter(lo, np.float32(np.inf)), np.nextafter(hi, np.float32(0)), hi, 1e6], np.float32)
    pts = np.zeros((5, 4), np.float32)
    pts[:, 0] = r
    proj = _no_warnings(project, pts, SPEC)
    assert proj.valid.tolist() == [False, True, True, False, False]
    # all share one pixel: the nearest valid point wins
    assert proj.point_index_img[proj.mask].tolist() == [1]


def test_non_finite_points_are_invalid_and_flagged():
    pts = np.array(
        [[np.nan, 1, 1, 0], [np.inf, 0, 0, 0], [1, -np.inf, 0, 0], [10, 0, 0, np.nan], [10, 1, 0, 0.5]], np.float32
    )
    proj = _no_warnings(project, pts, SPEC)
    _check_clean(proj, 5)
    assert proj.valid.tolist() == [False, False, False, False, True]
    assert proj.point_row[:4].tolist() == [-1] * 4 and proj.point_col[:4].tolist() == [-1] * 4
    assert proj.mask.sum() == 1 and proj.point_index_img[proj.mask][0] == 4


def test_huge_coordinates():
    big = np.finfo(np.float32).max
    pts = np.array([[big, big, big, 1.0], [-big, 1.0, -big, 0.0], [1e20, 1e-20, 0, 0], [10, 0, 0, 1e30]], np.float32)
    proj = _no_warnings(project, pts, SPEC)
    _check_clean(proj, 4)
    assert proj.valid.tolist() == [False, False, False, True]
    assert proj.intensity_img.max() == 1.0  # clipped


def test_encode_decode_garbage_images():
    d = np.array([[np.nan, np.inf, -np.inf, -5.0, 0.0, 1e30, 40.0]], np.float32)
    i = np.array([[0.5, np.nan, 2.0, -1.0, np.inf, 0.5, np.nan]], np.float32)
    spec = RangeImageSpec(1, 7, 3.0, -25.0, 1.45, 80.0)
    img = _no_warnings(encode, d, i, spec)
    assert img[:, 0, :6].tolist() == [[-1.0] * 6, [-1.0] * 6]
    assert img[1, 0, 6] == -1.0 and img[0, 0, 6] > -1.0  # NaN intensity -> 0
    junk = np.array([[[np.nan, 5.0, -7.0, np.inf, 0.3]], [[np.nan, 9.0, -9.0, 0.0, np.nan]]], np.float32)
    rng, inten, mask = _no_warnings(decode, junk, RangeImageSpec(1, 5, 3.0, -25.0, 1.45, 80.0))
    assert np.isfinite(rng).all() and np.isfinite(inten).all()
    assert mask.tolist() == [[False, False, False, False, True]]  # x >= 1 decodes to max_range: excluded


def _points_in_fov(draw, spec, n):
    """Random points strictly inside the range limits and the vertical FOV."""
    elems = st.floats(0.0, 1.0, allow_nan=False, width=64)
    u = np.array(draw(st.lists(elems, min_size=3 * n, max_size=3 * n))).reshape(n, 3)
    margin = 1e-3
    r = spec.min_range * (1 + margin) + u[:, 0] * (spec.max_range * (1 - margin) - spec.min_range * (1 + margin))
    el = spec.fov_down + (spec.fov_up - spec.fov_down) * (margin + u[:, 1] * (1 - 2 * margin))
    az = -np.pi + 2 * np.pi * u[:, 2]
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el), u[:, 0]], 1)
    return pts.astype(np.float32)


@st.composite
def point_sets(draw):
    n = draw(st.integers(1, 300))
    return _points_in_fov(draw, SMALL, n)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(point_sets())
def test_property_round_trip_ranges_and_angles(pts):
    proj = project(pts, SMALL)
    assert proj.valid.all()
    won = proj.point_index_img[proj.mask]
    pts64 = pts[won, :3].astype(np.float64)
    back = unproject(proj.range_img, proj.intensity_img, SMALL, mask=proj.mask)
    assert len(back) == len(won)
    r_true = np.linalg.norm(pts64, axis=1)
    np.testing.assert_allclose(np.linalg.norm(back[:, :3].astype(np.float64), axis=1), r_true, rtol=2e-6)
    elev, azim = pixel_angles(SMALL)
    half_v = 0.5 * (SMALL.fov_up - SMALL.fov_down) / SMALL.height
    half_u = np.pi / SMALL.width
    el_true = np.arctan2(pts64[:, 2], np.hypot(pts64[:, 0], pts64[:, 1]))
    az_true = np.arctan2(pts64[:, 1], pts64[:, 0])
    rows, cols = np.nonzero(proj.mask)
    assert np.all(np.abs(el_true - elev[rows]) <= half_v * (1 + 1e-6))
    d_az = np.angle(np.exp(1j * (az_true - azim[cols])))
    assert np.all(np.abs(d_az) <= half_u * (1 + 1e-6))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(point_sets())
def test_property_winner_is_nearest(pts):
    # duplicate some points so pixels hold several candidates and exact ties
    pts = np.concatenate([pts, pts[::3], pts[::2] * np.float32(1.01)])
    proj = project(pts, SMALL)
    r = np.linalg.norm(pts[:, :3].astype(np.float64), axis=1).astype(np.float32)
    # the 1.01x copies may pass max_range: only such points may be dropped, and they win no pixel
    assert np.all(r[~proj.valid] >= np.float32(SMALL.max_range) * np.float32(1 - 1e-6))
    pix = proj.point_row.astype(np.int64) * SMALL.width + proj.point_col
    pix = np.where(proj.valid, pix, -1)  # invalid points fall into no pixel
    best = np.full(SMALL.height * SMALL.width, np.inf, np.float32)
    np.minimum.at(best, pix[proj.valid], r[proj.valid])
    flat_idx = proj.point_index_img.reshape(-1)
    filled = flat_idx >= 0
    assert np.array_equal(np.flatnonzero(filled), np.unique(pix[proj.valid]))
    assert np.array_equal(r[flat_idx[filled]], best[filled])
    # tie-break: the lowest index among the nearest
    for p in np.flatnonzero(filled)[:50]:
        cands = np.flatnonzero((pix == p) & (r == best[p]))
        assert flat_idx[p] == cands.min()


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(1.4501, 79.999, allow_nan=False), min_size=1, max_size=64))
def test_property_encode_decode_relative_range(values):
    spec = RangeImageSpec(1, 64, 3.0, -25.0, 1.45, 80.0)
    d = np.zeros((1, 64), np.float32)
    d[0, : len(values)] = values
    img = encode(d, np.zeros_like(d), spec)
    rng, _, mask = decode(img, spec)
    assert mask[0, : len(values)].all() and not mask[0, len(values) :].any()
    np.testing.assert_allclose(rng[0, : len(values)], d[0, : len(values)], rtol=1e-5)
