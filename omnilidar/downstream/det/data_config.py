"""The Pi3DET data configuration per platform (OpenPCDet's DATA_CONFIG, as data).

Pi3DET trains one detector per platform on a fixed point cloud range
``[0, -75.2, -2, 75.2, 75.2, 4]`` (x forward only) after shifting every point
and box by the platform's ``SHIFT_COOR`` (a translation, z in practice) so that
the ground of a drone (~10 m up) or a quadruped (0.65 m) sits where a car's
sensor sees it. Drone frames label Car only; Quadruped frames Car and
Pedestrian. Anchors follow OpenPCDet's KITTI ones (one size per class, headings
0 and 90 deg, bottom heights for a ground at about -1.7 m).

:func:`platform_config` turns the validated ``downstream.det`` section and a
platform name into a :class:`PlatformConfig`; :func:`anchor_generator_config`
gives the list that goes into the detector's ``DENSE_HEAD.ANCHOR_GENERATOR_CONFIG``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnilidar.errors import InputError
from omnilidar.io.pi3det import PLATFORM_CLASSES

PLATFORMS = {"drone": "Drone", "quadruped": "Quadruped", "vehicle": "Vehicle"}


@dataclass(frozen=True)
class PlatformConfig:
    platform: str                      # config key: drone, quadruped, vehicle
    name: str                          # Pi3DET platform name: Drone, Quadruped, Vehicle
    class_names: tuple[str, ...]       # detector classes, label ids 1..K in this order
    shift: tuple[float, float, float]  # SHIFT_COOR added to points and box centres
    point_cloud_range: tuple[float, ...]
    voxel_size: tuple[float, float, float]
    anchors: dict                      # class -> {size, rotations, bottom, matched, unmatched}

    @property
    def grid_size(self) -> np.ndarray:
        """Voxels along x, y, z (OpenPCDet's grid_size)."""
        pcr = np.asarray(self.point_cloud_range, np.float64)
        return np.round((pcr[3:6] - pcr[0:3]) / np.asarray(self.voxel_size, np.float64)).astype(np.int64)

    def as_dict(self) -> dict:
        return {"platform": self.platform, "name": self.name, "class_names": list(self.class_names),
                "shift": list(self.shift), "point_cloud_range": list(self.point_cloud_range),
                "voxel_size": list(self.voxel_size), "anchors": self.anchors}


def platform_config(settings: dict, platform: str) -> PlatformConfig:
    """The data configuration of one platform from the ``downstream.det`` section."""
    if platform not in PLATFORMS:
        raise InputError(None, f"unknown Pi3DET platform {platform!r}; known: {', '.join(PLATFORMS)}")
    spec = settings["platforms"].get(platform)
    if spec is None:
        raise InputError(None, f"downstream.det.platforms has no entry {platform!r}")
    name = PLATFORMS[platform]
    classes = tuple(spec["classes"])
    unknown = [c for c in classes if c not in PLATFORM_CLASSES[name]]
    if unknown:
        raise InputError(None, f"downstream.det.platforms.{platform}.classes: {unknown} are not annotated on "
                               f"{name} frames (annotated: {', '.join(PLATFORM_CLASSES[name])})")
    missing = [c for c in classes if c not in settings["anchors"]]
    if missing:
        raise InputError(None, f"downstream.det.anchors has no entry for class {missing[0]!r}")
    pcr = tuple(float(v) for v in settings["point_cloud_range"])
    voxel = tuple(float(v) for v in settings["voxel_size"])
    extent = np.asarray(pcr[3:]) - np.asarray(pcr[:3])
    if (extent <= 0).any():
        raise InputError(None, f"downstream.det.point_cloud_range {list(pcr)} is empty along an axis")
    cells = extent / np.asarray(voxel)
    if not np.allclose(cells, np.round(cells), atol=1e-4):
        raise InputError(None, f"downstream.det.voxel_size {list(voxel)} does not divide the point cloud range "
                               f"{list(pcr)} (cells {cells.round(3).tolist()})")
    if int(round(cells[0])) % 8 or int(round(cells[1])) % 8:
        raise InputError(None, f"downstream.det.voxel_size {list(voxel)}: the BEV grid {cells[:2].round().tolist()} "
                               f"must be a multiple of 8 (VoxelBackBone8x's stride)")
    return PlatformConfig(platform=platform, name=name, class_names=classes,
                          shift=tuple(float(v) for v in spec["shift"]), point_cloud_range=pcr,
                          voxel_size=voxel, anchors={c: dict(settings["anchors"][c]) for c in classes})


def anchor_generator_config(cfg: PlatformConfig) -> list[dict]:
    """OpenPCDet's ANCHOR_GENERATOR_CONFIG for the platform's classes."""
    return [{
        "class_name": c,
        "anchor_sizes": [list(cfg.anchors[c]["size"])],
        "anchor_rotations": list(cfg.anchors[c]["rotations"]),
        "anchor_bottom_heights": [float(cfg.anchors[c]["bottom"])],
        "align_center": False,
        "feature_map_stride": 8,
        "matched_threshold": float(cfg.anchors[c]["matched"]),
        "unmatched_threshold": float(cfg.anchors[c]["unmatched"]),
    } for c in cfg.class_names]
