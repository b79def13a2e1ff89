"""Sensor poses of the three platforms along a scene's route.

* vehicle: in the rightmost lane, sensor ``mount_height`` above the road;
* quadruped: walking along the middle of the right sidewalk, sensor
  ``mount_height`` above the pavement (so kerbs and parked cars occlude a lot);
* drone: over the road centre at ``mount_height`` above the ground, pitched
  down by the sensor's ``mount_pitch_deg``.

Consecutive poses are ``spacing`` metres apart along the route, centred on it,
with a little lateral and heading jitter (drivers and pilots are not rails).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnilidar.lidar.sensors import SensorSpec

PLATFORMS = ("vehicle", "drone", "quadruped")


@dataclass(frozen=True)
class SensorPose:
    """Sensor origin (world) and heading; pitch comes from the SensorSpec."""

    position: tuple[float, float, float]
    yaw: float

    def rotation(self, pitch_deg: float) -> np.ndarray:
        """Sensor-to-world rotation: yaw about z, then nose-down pitch about the sensor's y axis."""
        cy, sy = np.cos(self.yaw), np.sin(self.yaw)
        p = np.deg2rad(pitch_deg)
        cp, sp = np.cos(p), np.sin(p)
        rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
        ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])  # +pitch tilts +x down
        return rz @ ry


def route_poses(scene, platform: str, sensor: SensorSpec, num_scans: int, spacing: float,
                rng: np.random.Generator) -> list[SensorPose]:
    """``num_scans`` poses along the scene's route for ``platform``."""
    if platform not in PLATFORMS:
        raise ValueError(f"unknown platform {platform!r}; known: {', '.join(PLATFORMS)}")
    route = scene.route
    d = {"vehicle": route.lane_d, "quadruped": route.walk_d, "drone": route.centre_d}[platform]
    jitter = {"vehicle": 0.25, "quadruped": 0.1, "drone": 1.0}[platform]
    s = (np.arange(num_scans) - 0.5 * (num_scans - 1)) * spacing
    s = np.clip(s, route.s_start, route.s_end)
    lateral = d + rng.uniform(-jitter, jitter, num_scans)
    yaw_jitter = rng.normal(0.0, 0.02 if platform != "drone" else 0.1, num_scans)
    poses = []
    for k in range(num_scans):
        x, y, heading = scene.route_pose(float(s[k]), float(lateral[k]))
        z = float(scene.ground.height(np.array([x]), np.array([y]))[0]) + sensor.mount_height
        poses.append(SensorPose((x, y, z), float(heading + yaw_jitter[k])))
    return poses
