"""Ray caster: exact distances to analytic primitives, kerbs, and culling that never misses."""

from __future__ import annotations

import numpy as np
import pytest

from omnilidar.data.synthetic import raycast
from omnilidar.data.synthetic.ground import GroundMap
from omnilidar.data.synthetic.primitives import BOX, CYLINDER, ELLIPSOID, PrimitiveBuilder


def flat_ground(residual=None, res=0.2, size=200.0):
    n = int(size / res)
    res_map = np.zeros((n, n), np.float32) if residual is None else residual
    return GroundMap(x0=-size / 2, y0=-size / 2, res=res, plane=(0.0, 0.0, 0.0), residual=res_map,
                     semantic=np.full(res_map.shape, 72, np.uint16), reflectivity=np.full(res_map.shape, 0.5, np.float32))


def cast_one(ground, prims, origin, direction):
    """Cast a single ray by building a 1 x 1 sensor pointed along ``direction``."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    az = np.arctan2(d[1], d[0])
    el = np.arcsin(d[2])
    # one column at azimuth az: columns are pi - (c + 0.5) * 2pi / C with C = 1 -> az = 0; rotate instead.
    c, s = np.cos(az), np.sin(az)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    hits = raycast.cast(ground, prims, np.asarray(origin, float), rot, np.array([el]),
                        np.array([0.0]), 200.0)
    return hits.t[0], hits.hit[0], hits.normal[0]


def test_box_cylinder_ellipsoid_distances_are_exact():
    b = PrimitiveBuilder()
    b.add(BOX, (10.0, 0.0, 1.0), (1.0, 2.0, 1.0), 0.3, 50, 0, 0.5)
    b.add(CYLINDER, (0.0, 20.0, 1.0), (0.5, 0.5, 1.0), 0.0, 80, 0, 0.5)
    b.add(ELLIPSOID, (-15.0, 0.0, 1.0), (2.0, 1.0, 0.5), 0.0, 70, 0, 0.5)
    prims = b.build()
    g = flat_ground()
    o = (0.0, 0.0, 1.0)
    # Box yawed 0.3 rad: along +x the ray enters its face x_local = -1.
    t, hit, n = cast_one(g, prims, o, (1, 0, 0))
    assert hit == 0
    # Solve for the entry: in the box frame the ray is (t cos(-0.3) - 10 cos..., ...): compare numerically.
    ca, sa = np.cos(0.3), np.sin(0.3)
    ts = np.linspace(5, 12, 700001)
    lx = ca * (ts - 10.0)
    ly = -sa * (ts - 10.0)
    inside = (np.abs(lx) <= 1.0) & (np.abs(ly) <= 2.0)
    assert t == pytest.approx(ts[inside][0], abs=2e-5)
    t, hit, n = cast_one(g, prims, o, (0, 1, 0))
    assert hit == 1 and t == pytest.approx(19.5, abs=1e-9)
    assert n == pytest.approx([0, -1, 0], abs=1e-9)
    t, hit, n = cast_one(g, prims, o, (-1, 0, 0))
    assert hit == 2 and t == pytest.approx(13.0, abs=1e-9)
    assert n == pytest.approx([1, 0, 0], abs=1e-9)


def test_ground_plane_and_kerb():
    g = flat_ground()
    t, hit, n = cast_one(g, PrimitiveBuilder().build(), (0.0, 0.0, 2.0), (1.0, 0.0, -0.2))
    assert hit == raycast.GROUND_HIT
    assert t == pytest.approx(np.hypot(10.0, 2.0), rel=1e-6)
    assert n == pytest.approx([0, 0, 1], abs=1e-9)
    # A 0.15 m kerb at x >= 9: a shallow ray hits its vertical face at x = 9.
    res = 0.2
    n_cells = int(200.0 / res)
    residual = np.zeros((n_cells, n_cells), np.float32)
    xs = -100.0 + (np.arange(n_cells) + 0.5) * res
    residual[:, xs >= 9.0] = 0.15
    g = flat_ground(residual)
    direction = np.array([1.0, 0.0, -0.011])
    t, hit, n = cast_one(g, PrimitiveBuilder().build(), (0.0, 0.0, 0.2), direction)
    x_hit = t * direction[0] / np.linalg.norm(direction)
    assert hit == raycast.GROUND_HIT
    assert x_hit == pytest.approx(9.0, abs=0.01)
    assert n == pytest.approx([-1, 0, 0], abs=1e-9)


def test_culling_never_misses_a_hit():
    rng = np.random.default_rng(0)
    b = PrimitiveBuilder()
    for _ in range(150):
        kind = int(rng.integers(3))
        b.add(kind, (rng.uniform(-40, 40), rng.uniform(-40, 40), rng.uniform(-0.5, 6)), rng.uniform(0.1, 4, 3),
              rng.uniform(-np.pi, np.pi), 50, 0, 0.5)
    b.add(BOX, (0.5, 0.3, 1.0), (2.0, 2.0, 0.2), 0.2, 50, 0, 0.5)  # right above/around the sensor
    prims = b.build()
    g = flat_ground()
    elev = np.deg2rad(np.linspace(25, -40, 24))
    n_cols = 180
    azim = np.pi - (np.arange(n_cols) + 0.5) * 2 * np.pi / n_cols
    pitch = np.deg2rad(15)
    rot = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    origin = np.array([1.0, -2.0, 1.7])
    culled = raycast.cast(g, prims, origin, rot, elev, azim, 80.0)
    # Brute force: every primitive against every ray.
    ce, se = np.cos(elev), np.sin(elev)
    d_s = np.stack([np.cos(azim)[:, None] * ce, np.sin(azim)[:, None] * ce,
                    np.broadcast_to(se, (n_cols, len(elev)))], -1).reshape(-1, 3)
    dirs = np.ascontiguousarray(d_s @ rot.T)
    t = np.where(culled.hit == raycast.GROUND_HIT, culled.t, 80.0).astype(np.float64)
    t = np.where(culled.hit >= 0, 80.0, t)
    # recompute ground-only first, then all primitives unculled
    ground_only = raycast.cast(g, PrimitiveBuilder().build(), origin, rot, elev, azim, 80.0)
    t = np.where(np.isfinite(ground_only.t), ground_only.t, 80.0)
    hit = np.where(np.isfinite(ground_only.t), raycast.GROUND_HIT, raycast.NO_HIT).astype(np.int32)
    normal = np.zeros((len(t), 3))
    P = len(prims)
    raycast._primitive_kernel(origin, dirs, len(elev), n_cols, prims.kind, prims.center, prims.half, prims.yaw,
                              np.zeros(P, np.int64), np.full(P, n_cols, np.int64), np.zeros(P, np.int64),
                              np.full(P, len(elev) - 1, np.int64), t, hit, normal)
    assert (hit == culled.hit).all()
    hit_any = hit != raycast.NO_HIT
    assert np.allclose(t[hit_any], culled.t[hit_any])
    assert (culled.hit >= 0).sum() > 100
