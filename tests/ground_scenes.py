"""Small ray-cast test scenes for ground estimation (helper for tests and benchmarks).

A world with +z up: a (possibly sloped) ground plane, raised sidewalk slabs
(ground), cars, walls, poles and pedestrians (not ground). Rays are the sensor's
beams x azimuths, rotated by its mount pitch; each ray returns its nearest hit.
Semantic ids are raw SemanticKITTI ids (40 road, 48 sidewalk, 10 car, 50
building, 80 pole, 30 person).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec


def _ray_box(o, d, lo, hi):
    """Entry distance of rays (origin o (3,), directions d (R, 3)) into an
    axis-aligned box; inf where missed."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (tmax >= tmin) & (tmax > 0)
    return np.where(hit, np.maximum(tmin, 0.0), np.inf)


def _ray_cylinder(o, d, cx, cy, radius, z0, z1):
    """Entry distance into a vertical cylinder; inf where missed."""
    ox, oy = o[0] - cx, o[1] - cy
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2 * (ox * d[:, 0] + oy * d[:, 1])
    c = ox**2 + oy**2 - radius**2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(disc)) / (2 * a)
    zt = o[2] + t * d[:, 2]
    hit = (disc >= 0) & (a > 1e-12) & (t > 0) & (zt >= z0) & (zt <= z1)
    return np.where(hit, t, np.inf)


def make_scene(
    sensor: SensorSpec,
    rng: np.random.Generator,
    *,
    slope_deg: tuple[float, float] = (0.0, 0.0),
    azimuth_steps: int = 512,
    n_cars: int = 8,
    n_poles: int = 10,
    n_people: int = 4,
    extent: float = 40.0,
) -> Scan:
    """Ray-cast one scan of a random scene seen from ``sensor`` at its mount
    height and pitch. ``slope_deg`` tilts the ground plane about y and x."""
    H = sensor.mount_height
    sx, sy = np.tan(np.deg2rad(slope_deg))
    gz = lambda x, y: -H + sx * x + sy * y  # noqa: E731  ground height at (x, y)

    # Rays: beams x azimuths in the sensor frame, rotated into the world frame.
    el = sensor.elevations_rad[:, None]
    az = np.linspace(np.pi, -np.pi, azimuth_steps, endpoint=False)[None, :]
    ds = np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], axis=-1
    ).reshape(-1, 3)
    phi = np.deg2rad(sensor.mount_pitch_deg)
    c, s = np.cos(phi), np.sin(phi)
    dw = np.stack([c * ds[:, 0] + s * ds[:, 2], ds[:, 1], -s * ds[:, 0] + c * ds[:, 2]], axis=1)
    o = np.zeros(3)

    # Ground plane: z = -H + sx x + sy y.
    denom = dw[:, 2] - sx * dw[:, 0] - sy * dw[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = np.where(denom < -1e-9, -H / denom, np.inf)
    best = t_plane.copy()
    label = np.full(len(dw), 40, np.uint16)

    def place(t, lab):
        nonlocal best
        closer = t < best
        best = np.where(closer, t, best)
        label[closer] = lab

    # Objects are placed in a ring around the sensor, not on top of it.
    def spot(rmin=4.0):
        r = rng.uniform(rmin, extent)
        a = rng.uniform(-np.pi, np.pi)
        return r * np.cos(a), r * np.sin(a)

    # Sidewalk slabs (ground, 0.15 m curb following the slope) along both
    # sides, each with a building wall behind it.
    for side in (-1, 1):
        y0 = side * rng.uniform(5.0, 7.0)
        y1 = y0 + side * 3.0
        ylo, yhi = min(y0, y1), max(y0, y1)
        # Top face: the ground plane raised by 0.15 m, within ylo..yhi.
        with np.errstate(divide="ignore", invalid="ignore"):
            t_top = np.where(denom < -1e-9, (-H + 0.15) / denom, np.inf)
        with np.errstate(invalid="ignore"):
            yt = t_top * dw[:, 1]
        t_top = np.where((yt >= ylo) & (yt <= yhi), t_top, np.inf)
        # Curb face: the vertical plane y = y0 between road and sidewalk top.
        with np.errstate(divide="ignore", invalid="ignore"):
            t_curb = np.where(np.abs(dw[:, 1]) > 1e-9, y0 / dw[:, 1], np.inf)
        t_curb = np.where(t_curb > 0, t_curb, np.inf)
        with np.errstate(invalid="ignore"):
            xc, zc = t_curb * dw[:, 0], t_curb * dw[:, 2]
        with np.errstate(invalid="ignore"):
            above = zc - gz(xc, y0)
        t_curb = np.where((above >= 0) & (above <= 0.15), t_curb, np.inf)
        # The road plane does not exist under the slab.
        with np.errstate(invalid="ignore"):
            yp = best * dw[:, 1]
        best = np.where(np.isfinite(best) & (yp >= ylo) & (yp <= yhi), np.inf, best)
        place(np.minimum(t_top, t_curb), 48)
        lo = np.array([-extent, min(y1, y1 + side * 1.0), -H - 10.0])
        hi = np.array([extent, max(y1, y1 + side * 1.0), gz(0, y1) + 8.0])
        place(_ray_box(o, dw, lo, hi), 50)
    for _ in range(n_cars):
        x, y = spot()
        y = float(np.clip(y, -4.0, 4.0))
        g = gz(x, y)
        lo = np.array([x - 2.0, y - 0.9, g + 0.25])
        hi = np.array([x + 2.0, y + 0.9, g + 1.5])
        place(_ray_box(o, dw, lo, hi), 10)
    for _ in range(n_poles):
        x, y = spot()
        place(_ray_cylinder(o, dw, x, y, 0.12, gz(x, y) - 0.1, gz(x, y) + 5.0), 80)
    for _ in range(n_people):
        x, y = spot()
        g = gz(x, y)
        place(_ray_box(o, dw, np.array([x - 0.25, y - 0.3, g]), np.array([x + 0.25, y + 0.3, g + 1.75])), 30)

    hit = np.isfinite(best) & (best >= sensor.min_range) & (best <= sensor.max_range)
    r = best[hit] + rng.normal(0.0, sensor.range_noise_std, hit.sum())
    xyz = ds[hit] * r[:, None]
    intensity = rng.uniform(0.0, 0.6, hit.sum())
    pts = np.concatenate([xyz, intensity[:, None]], axis=1).astype(np.float32)
    return Scan(points=pts, semantic=label[hit], instance=np.zeros(hit.sum(), np.uint16))


def platform_sensors() -> dict[str, SensorSpec]:
    """The three platforms' sensors (presets)."""
    from omnilidar.lidar.sensors import PRESETS

    return {
        "vehicle": PRESETS["kitti_hdl64e"],
        "drone": PRESETS["drone_os64"],
        "quadruped": PRESETS["quadruped_os64"],
    }


def tilted(sensor: SensorSpec, extra_pitch_deg: float) -> SensorSpec:
    """The same sensor mounted with a different pitch (for pose errors)."""
    return replace(sensor, mount_pitch_deg=sensor.mount_pitch_deg + extra_pitch_deg)
