"""Sensor specifications and presets for the platforms OmniLiDAR covers.

Angles are stored in degrees (as data sheets give them); helpers return radians.
Beam 0 is the top (highest elevation) beam, matching range-image row 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _hdl64e_elevations() -> tuple[float, ...]:
    # HDL-64E S2 as mounted on the KITTI car: upper block of 32 lasers from +2.0 deg
    # down to -8.33 deg (1/3 deg pitch), lower block of 32 from -8.83 to -24.33 deg
    # (1/2 deg pitch); total vertical field of view 26.9 deg.
    upper = 2.0 - np.arange(32) * (1.0 / 3.0)
    lower = -8.83 - np.arange(32) * 0.5
    return tuple(float(a) for a in np.concatenate([upper, lower]))


def _uniform(top: float, bottom: float, n: int) -> tuple[float, ...]:
    return tuple(float(a) for a in np.linspace(top, bottom, n))


@dataclass(frozen=True)
class SensorSpec:
    """Geometry and radiometry of a spinning LiDAR on a platform.

    beam_elevations_deg: per-beam elevation angles, descending (beam 0 = top).
    azimuth_steps: firings per revolution (points per beam per sweep).
    fov_up_deg / fov_down_deg: vertical field of view used for range-image
        projection (R2DM convention; KITTI uses +3 / -25 deg for 64 rows).
    mount_height: sensor height above the ground plane (m).
    mount_pitch_deg: nose-down pitch of the sensor (positive tilts beams down).
        Scans are stored in the gravity-levelled frame centred at the sensor (x
        along the platform heading, z up), so that 7-DoF boxes stay valid; range
        images and ring recovery rotate them into the sensor's own frame
        (``levelled_to_sensor``). For level mounts both frames coincide.
    min_range / max_range: valid returns (m); the projection masks outside them.
    intensity_scale: the dataset's intensity unit (1.0 for KITTI's 0..1,
        255.0 for nuScenes' 0..255). Effects convert to 0..1 physical
        reflectance internally.
    range_noise_std: 1-sigma range noise of a return (m).
    beam_divergence_mrad: full-angle beam divergence (used by weather effects).
    """

    name: str
    beam_elevations_deg: tuple[float, ...]
    azimuth_steps: int
    fov_up_deg: float
    fov_down_deg: float
    mount_height: float
    mount_pitch_deg: float = 0.0
    min_range: float = 1.45
    max_range: float = 80.0
    intensity_scale: float = 1.0
    range_noise_std: float = 0.02
    beam_divergence_mrad: float = 3.0
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def num_beams(self) -> int:
        return len(self.beam_elevations_deg)

    @property
    def elevations_rad(self) -> np.ndarray:
        return np.deg2rad(np.asarray(self.beam_elevations_deg, dtype=np.float64))

    @property
    def azimuths_rad(self) -> np.ndarray:
        """Firing azimuths of one revolution, in firing order.

        KITTI's HDL-64E spins clockwise seen from above and each sweep starts
        behind the car; we fire from +pi decreasing to -pi (atan2 convention).
        """
        step = 2.0 * np.pi / self.azimuth_steps
        return np.pi - (np.arange(self.azimuth_steps) + 0.5) * step


def levelled_to_sensor(xyz: np.ndarray, pitch_deg: float) -> np.ndarray:
    """Rotate (N, 3) points from the levelled frame into a sensor pitched nose-down by
    ``pitch_deg`` (positive tilts the sensor's +x axis down); identity at 0."""
    if pitch_deg == 0.0:
        return xyz
    p = np.deg2rad(pitch_deg)
    c, s = np.cos(p), np.sin(p)
    x, z = xyz[:, 0], xyz[:, 2]
    return np.stack([c * x - s * z, xyz[:, 1], s * x + c * z], axis=1)


def sensor_to_levelled(xyz: np.ndarray, pitch_deg: float) -> np.ndarray:
    """Inverse of :func:`levelled_to_sensor`."""
    return levelled_to_sensor(xyz, -pitch_deg)


# Presets. Parameter choices (see docs/datasets.md "Sensors"):
#  - kitti_hdl64e: KITTI/SemanticKITTI car, HDL-64E at 1.73 m, ~0.17 deg azimuth
#    step at 10 Hz (2083 firings/rev); range image 64x1024 over +3/-25 deg (R2DM).
#  - nuscenes_hdl32e: HDL-32E at 1.84 m, +10.67..-30.67 deg in 1.33 deg steps,
#    20 Hz -> 1085 firings/rev (~34.7k points per sweep, as the real sample); 0..255.
#  - drone_os64 / quadruped_os64: Pi3DET is recorded with Ouster OS1-64 sensors
#    (M3ED): 64 uniform beams over +-22.5 deg, 1024 columns. The drone flies at
#    ~10 m with the sensor pitched 20 deg nose-down so near ground is in view;
#    the quadruped (Spot) carries it at 0.65 m, level.
PRESETS: dict[str, SensorSpec] = {
    "kitti_hdl64e": SensorSpec(
        name="kitti_hdl64e",
        beam_elevations_deg=_hdl64e_elevations(),
        azimuth_steps=2083,
        fov_up_deg=3.0,
        fov_down_deg=-25.0,
        mount_height=1.73,
        min_range=1.45,
        max_range=80.0,
        intensity_scale=1.0,
    ),
    "nuscenes_hdl32e": SensorSpec(
        name="nuscenes_hdl32e",
        beam_elevations_deg=_uniform(10.67, -30.67, 32),
        azimuth_steps=1085,
        fov_up_deg=10.67,
        fov_down_deg=-30.67,
        mount_height=1.84,
        min_range=1.0,
        max_range=70.0,
        intensity_scale=255.0,
    ),
    "drone_os64": SensorSpec(
        name="drone_os64",
        beam_elevations_deg=_uniform(22.5, -22.5, 64),
        azimuth_steps=1024,
        fov_up_deg=22.5,
        fov_down_deg=-22.5,
        mount_height=10.0,
        mount_pitch_deg=20.0,
        min_range=1.0,
        max_range=80.0,
        intensity_scale=1.0,
    ),
    "quadruped_os64": SensorSpec(
        name="quadruped_os64",
        beam_elevations_deg=_uniform(22.5, -22.5, 64),
        azimuth_steps=1024,
        fov_up_deg=22.5,
        fov_down_deg=-22.5,
        mount_height=0.65,
        min_range=0.5,
        max_range=80.0,
        intensity_scale=1.0,
    ),
}


def get_sensor(name: str) -> SensorSpec:
    from omnilidar.errors import InputError

    try:
        return PRESETS[name]
    except KeyError:
        raise InputError(None, f"unknown sensor preset {name!r}; known: {', '.join(sorted(PRESETS))}") from None
