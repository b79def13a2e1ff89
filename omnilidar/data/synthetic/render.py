"""One sweep of a sensor in a scene: ray cast, radiometry, noise, labels, boxes.

Output frame: the LEVELLED sensor frame (origin at the sensor, x along the
platform heading, z up against gravity). For level sensors (vehicle, quadruped)
it is the sensor frame itself; for the pitched drone sensor the points are
rotated back by the mount pitch, which is what Pi3DET-style 7-DoF boxes need.

Point order (``point_order``):

* ``azimuth_major`` (default): firing order of a spinning sensor - for each
  azimuth step (``SensorSpec.azimuths_rad``, starting behind the sensor and
  sweeping clockwise seen from above), all beams top to bottom (ring 0 first).
  Real KITTI orders a column by laser id, which interleaves the HDL-64E's two
  blocks; we order by ring (elevation) instead, so a column is monotone in
  elevation.
* ``ring_major``: the layout of the distributed KITTI ``.bin`` files - one ring
  after another (top ring first), each ring a full revolution counter-clockwise
  starting straight ahead (azimuth 0). Ring-recovery heuristics that count
  azimuth wraps work on this order only.
"""

from __future__ import annotations

import numpy as np

from omnilidar.data.synthetic import classes as C
from omnilidar.data.synthetic import radiometry, raycast
from omnilidar.data.synthetic.trajectory import SensorPose
from omnilidar.lidar.scan import Boxes, Scan
from omnilidar.lidar.sensors import SensorSpec

POINT_ORDERS = ("azimuth_major", "ring_major")


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def render_scan(scene, sensor: SensorSpec, pose: SensorPose, rng: np.random.Generator, radiometry_settings: dict,
                point_order: str = "azimuth_major", min_box_points: int = 5) -> Scan:
    """Simulate one sweep of ``sensor`` at ``pose`` in ``scene``.

    Returns a Scan with points (x, y, z, intensity in the sensor's native scale),
    raw SemanticKITTI semantics, instance ids, rings (0 = top beam) and the boxes
    of Car / Pedestrian instances that have at least ``min_box_points`` points.
    """
    if point_order not in POINT_ORDERS:
        raise ValueError(f"unknown point order {point_order!r}; known: {', '.join(POINT_ORDERS)}")
    elev = sensor.elevations_rad
    azim = sensor.azimuths_rad
    B, Cn = len(elev), len(azim)
    rotation = pose.rotation(sensor.mount_pitch_deg)
    origin = np.asarray(pose.position, dtype=np.float64)
    hits = raycast.cast(scene.ground, scene.prims, origin, rotation, elev, azim, sensor.max_range)

    n = B * Cn
    ground = scene.ground
    is_prim = hits.hit >= 0
    is_ground = hits.hit == raycast.GROUND_HIT
    prim_idx = np.where(is_prim, hits.hit, 0)
    cell = np.where(hits.cell >= 0, hits.cell, 0)
    semantic = np.where(is_prim, scene.prims.semantic[prim_idx] if len(scene.prims) else 0,
                        np.where(hits.cell >= 0, ground.semantic.ravel()[cell], C.TERRAIN)).astype(np.uint16)
    instance = np.where(is_prim, scene.prims.instance[prim_idx] if len(scene.prims) else 0, 0).astype(np.uint16)
    refl = np.where(is_prim, scene.prims.reflectivity[prim_idx] if len(scene.prims) else 0.3,
                    np.where(hits.cell >= 0, ground.reflectivity.ravel()[cell], 0.4))

    # Ray directions in the sensor frame, column-major (same as the caster).
    ce, se = np.cos(elev), np.sin(elev)
    d_sensor = np.stack([np.cos(azim)[:, None] * ce[None, :], np.sin(azim)[:, None] * ce[None, :],
                         np.broadcast_to(se[None, :], (Cn, B))], axis=-1).reshape(-1, 3)
    d_world = d_sensor @ rotation.T
    cos_inc = np.abs(np.einsum("ij,ij->i", hits.normal, d_world))

    # Every draw below is full-length so the stream does not depend on hit counts.
    t = hits.t + rng.normal(0.0, sensor.range_noise_std, n)
    finite = np.isfinite(hits.t)
    t_safe = np.where(finite, hits.t, 1.0)
    detected = radiometry.detect(refl, cos_inc, t_safe, radiometry_settings, rng)
    native = float(sensor.intensity_scale)
    # KITTI stores two decimals (max 0.99); 0..255 sensors store integers.
    quantum, top = (0.01, 0.99) if native == 1.0 else (1.0 / native, 1.0)
    intensity = radiometry.remission(refl, cos_inc, t_safe, radiometry_settings, rng, quantum=quantum, top=top)
    valid = finite & (is_ground | is_prim) & detected & (t >= sensor.min_range) & (t <= sensor.max_range)

    # Levelled output frame: undo only the yaw (sensor frame pitched back).
    cy, sy = np.cos(pose.yaw), np.sin(pose.yaw)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    d_out = d_world @ rz  # = rz^T applied to world directions
    ring = np.tile(np.arange(B, dtype=np.int16), Cn)

    if point_order == "ring_major":
        # Rings top first; within a ring counter-clockwise from azimuth 0 (as KITTI files).
        az_ccw = np.mod(azim, 2.0 * np.pi)
        col_order = np.argsort(az_ccw, kind="stable")
        order = (np.arange(B)[:, None] + col_order[None, :] * B).ravel()
    else:
        order = np.arange(n)
    order = order[valid[order]]

    xyz = (d_out[order] * t[order, None]).astype(np.float32)
    inten = intensity[order] if native == 1.0 else np.round(intensity[order] * native)
    points = np.concatenate([xyz, inten[:, None].astype(np.float32)], axis=1)
    sem, inst = semantic[order], instance[order]

    # Boxes of Car / Pedestrian instances seen with enough points, in the output frame.
    keep_boxes = np.zeros(len(scene.boxes), bool)
    if len(scene.boxes):
        counts = np.bincount(inst, minlength=int(scene.box_instance.max()) + 1)
        wanted = np.isin(scene.box_semantic, list(C.BOX_NAMES))
        keep_boxes = wanted & (counts[scene.box_instance] >= min_box_points)
    if keep_boxes.any():
        wb = scene.boxes[keep_boxes]
        centre = (wb[:, :3] - origin) @ rz
        heading = _wrap(wb[:, 6] - pose.yaw)
        lidar_boxes = np.concatenate([centre, wb[:, 3:6], heading[:, None]], axis=1)
        names = np.array([C.BOX_NAMES[int(s)] for s in scene.box_semantic[keep_boxes]])
        boxes = Boxes(lidar_boxes.astype(np.float32), names, scene.box_instance[keep_boxes])
    else:
        boxes = Boxes.empty()
    return Scan(points=points, semantic=sem, instance=inst, ring=ring[order], boxes=boxes,
                intensity_scale=float(sensor.intensity_scale))
