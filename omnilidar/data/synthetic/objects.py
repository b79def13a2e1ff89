"""Object models: how a car, a tree or a pedestrian is built from primitives.

Each builder appends primitives (in the object's own yaw frame, standing on the
ground at height ``z0``) and returns the object's 3D box (x, y, z_center, dx, dy,
dz, heading) in the world frame, which tightly encloses its primitives.
"""

from __future__ import annotations

import numpy as np

from omnilidar.data.synthetic import classes as C
from omnilidar.data.synthetic.primitives import BOX, CYLINDER, ELLIPSOID, PrimitiveBuilder


def _place(x: float, y: float, yaw: float, lx: float, ly: float) -> tuple[float, float]:
    """World position of a point at (lx, ly) in an object frame at (x, y, yaw)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return x + c * lx - s * ly, y + s * lx + c * ly


def _refl(rng: np.random.Generator, cls_range: tuple[float, float]) -> float:
    return float(rng.uniform(*cls_range))


def vehicle(b: PrimitiveBuilder, rng: np.random.Generator, x, y, z0, yaw, semantic: int, instance: int,
            length: float, width: float, height: float) -> tuple:
    """Car / van / truck: wheels, a body and (cars) a cabin or (trucks) a cab and a cargo box."""
    paint = _refl(rng, C.REFLECTIVITY[semantic])
    tyre = _refl(rng, C.TYRE_REFLECTIVITY)
    wheel_r = 0.32 if semantic == C.CAR else 0.48
    clearance = 0.28 if semantic == C.CAR else 0.45
    wx = length / 2 - max(0.75, 0.18 * length)
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            px, py = _place(x, y, yaw, sx * wx, sy * (width / 2 - 0.13))
            b.add(BOX, (px, py, z0 + wheel_r), (wheel_r, 0.11, wheel_r), yaw, semantic, instance, tyre)
    if semantic == C.TRUCK:
        cab_l = 2.3
        px, py = _place(x, y, yaw, length / 2 - cab_l / 2, 0.0)
        cab_h = min(height, 3.0)
        b.add(BOX, (px, py, z0 + clearance + (cab_h - clearance) / 2), (cab_l / 2, width / 2, (cab_h - clearance) / 2),
              yaw, semantic, instance, paint)
        cargo_l = length - cab_l - 0.2
        px, py = _place(x, y, yaw, -length / 2 + cargo_l / 2, 0.0)
        base = clearance + 0.6
        b.add(BOX, (px, py, z0 + (base + height) / 2), (cargo_l / 2, width / 2, (height - base) / 2),
              yaw, semantic, instance, _refl(rng, C.REFLECTIVITY[semantic]))
    elif semantic == C.CAR:
        body_top = clearance + 0.55 * (height - clearance)
        b.add(BOX, (x, y, z0 + (clearance + body_top) / 2), (length / 2, width / 2, (body_top - clearance) / 2),
              yaw, semantic, instance, paint)
        cab_l = 0.52 * length
        px, py = _place(x, y, yaw, -0.06 * length, 0.0)
        glassy = paint * 0.35 + 0.01  # windows: dark, often no or zero-remission returns
        b.add(BOX, (px, py, z0 + (body_top + height) / 2), (cab_l / 2, 0.44 * width, (height - body_top) / 2),
              yaw, semantic, instance, glassy)
    else:  # van / bus / other vehicle: one tall body
        b.add(BOX, (x, y, z0 + (clearance + height) / 2), (length / 2, width / 2, (height - clearance) / 2),
              yaw, semantic, instance, paint)
    return (x, y, z0 + height / 2, length, width, height, yaw)


def person(b: PrimitiveBuilder, rng: np.random.Generator, x, y, z0, yaw, semantic: int, instance: int,
           height: float) -> tuple:
    """Pedestrian: two legs (cylinders), torso (ellipsoid), head (sphere)."""
    refl = _refl(rng, C.REFLECTIVITY[semantic])
    leg_h = 0.47 * height
    stride = rng.uniform(0.0, 0.25)
    for sgn in (-1.0, 1.0):
        px, py = _place(x, y, yaw, sgn * stride / 2, sgn * 0.1)
        b.add(CYLINDER, (px, py, z0 + leg_h / 2), (0.075, 0.075, leg_h / 2), yaw, semantic, instance, refl * 0.8)
    torso_h = 0.33 * height
    b.add(ELLIPSOID, (x, y, z0 + leg_h + torso_h / 2), (0.14, 0.24, torso_h / 2 + 0.03), yaw, semantic, instance, refl)
    head_r = 0.1 * height / 1.75 + 0.01
    b.add(ELLIPSOID, (x, y, z0 + height - head_r), (head_r, head_r * 0.9, head_r), yaw, semantic, instance, refl)
    dx = 0.3 + stride + 0.16
    return (x, y, z0 + height / 2, max(dx, 0.5), 0.56, height, yaw)


def bicycle(b: PrimitiveBuilder, rng: np.random.Generator, x, y, z0, yaw, semantic: int, instance: int,
            rider_height: float | None) -> tuple:
    """Bicycle (two thin wheel discs and a frame), optionally with a rider (bicyclist)."""
    refl = _refl(rng, C.REFLECTIVITY[semantic])
    for lx in (-0.55, 0.55):
        px, py = _place(x, y, yaw, lx, 0.0)
        b.add(BOX, (px, py, z0 + 0.35), (0.33, 0.025, 0.33), yaw, semantic, instance, refl * 0.5)
    b.add(BOX, (x, y, z0 + 0.7), (0.5, 0.03, 0.2), yaw, semantic, instance, refl)
    top = 1.1
    if rider_height is not None:
        px, py = _place(x, y, yaw, -0.15, 0.0)
        b.add(CYLINDER, (px, py, z0 + 0.75), (0.09, 0.09, 0.3), yaw, semantic, instance, refl)
        px, py = _place(x, y, yaw, -0.05, 0.0)
        b.add(ELLIPSOID, (px, py, z0 + 1.3), (0.22, 0.2, 0.3), yaw, semantic, instance, refl)
        b.add(ELLIPSOID, (x + 0.0, y + 0.0, z0 + rider_height - 0.1), (0.1, 0.1, 0.11), yaw, semantic, instance, refl)
        top = rider_height
    return (x, y, z0 + top / 2, 1.8, 0.6, top, yaw)


def tree(b: PrimitiveBuilder, rng: np.random.Generator, x, y, z0, scale: float = 1.0) -> float:
    """Street or park tree: trunk (cylinder) and crown (ellipsoid). Returns the crown radius."""
    trunk_r = rng.uniform(0.1, 0.28) * scale
    trunk_h = rng.uniform(1.6, 3.2) * scale
    crown_h = rng.uniform(1.4, 3.2) * scale
    crown_r = rng.uniform(1.4, 3.3) * scale
    b.add(CYLINDER, (x, y, z0 + trunk_h / 2 - 0.1), (trunk_r, trunk_r, trunk_h / 2 + 0.1), 0.0, C.TRUNK, 0,
          _refl(rng, C.REFLECTIVITY[C.TRUNK]))
    ratio = rng.uniform(0.8, 1.15)
    b.add(ELLIPSOID, (x, y, z0 + trunk_h + 0.8 * crown_h), (crown_r, crown_r * ratio, crown_h),
          rng.uniform(0, np.pi), C.VEGETATION, 0, _refl(rng, C.REFLECTIVITY[C.VEGETATION]))
    return crown_r


def bush(b: PrimitiveBuilder, rng: np.random.Generator, x, y, z0) -> float:
    r = rng.uniform(0.5, 1.8)
    h = rng.uniform(0.5, 1.3)
    b.add(ELLIPSOID, (x, y, z0 + 0.6 * h), (r, r * rng.uniform(0.7, 1.3), h), rng.uniform(0, np.pi),
          C.VEGETATION, 0, _refl(rng, C.REFLECTIVITY[C.VEGETATION]))
    return r


def wall(b: PrimitiveBuilder, rng: np.random.Generator, x, y, z0, yaw, length: float, thickness: float,
         height: float, semantic: int) -> None:
    """Hedge (vegetation), fence or building block: a box standing on the ground
    (sunk 0.3 m so that sloping ground never shows a gap)."""
    b.add(BOX, (x, y, z0 + (height - 0.3) / 2), (length / 2, thickness / 2, (height + 0.3) / 2), yaw, semantic, 0,
          _refl(rng, C.REFLECTIVITY[semantic]))


def pole(b: PrimitiveBuilder, rng: np.random.Generator, x, y, z0, yaw_to_road: float, sign: bool) -> None:
    """Street light (tall pole with an arm) or traffic sign (short pole with a plate facing traffic)."""
    refl = _refl(rng, C.REFLECTIVITY[C.POLE])
    if sign:
        h = rng.uniform(2.4, 3.2)
        r = rng.uniform(0.035, 0.06)
        b.add(CYLINDER, (x, y, z0 + h / 2), (r, r, h / 2), 0.0, C.POLE, 0, refl)
        size = rng.uniform(0.3, 0.45)
        # Plate faces along the road (its thin axis is the road direction).
        b.add(BOX, (x, y, z0 + h + size * 0.8), (0.02, size, size), yaw_to_road + 0.5 * np.pi, C.TRAFFIC_SIGN, 0,
              _refl(rng, C.REFLECTIVITY[C.TRAFFIC_SIGN]))
    else:
        h = rng.uniform(5.0, 9.0)
        r = rng.uniform(0.08, 0.15)
        b.add(CYLINDER, (x, y, z0 + h / 2), (r, r, h / 2), 0.0, C.POLE, 0, refl)
        arm = rng.uniform(0.8, 2.0)
        px, py = _place(x, y, yaw_to_road, arm / 2, 0.0)
        b.add(BOX, (px, py, z0 + h - 0.1), (arm / 2, 0.06, 0.06), yaw_to_road, C.POLE, 0, refl)
