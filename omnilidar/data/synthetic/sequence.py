"""A sequence: consecutive scans along a trajectory through one generated scene.

Seeds: every shard derives a ``np.random.SeedSequence`` from (root seed,
dataset, shard); scene k of a shard and scan j of that scene get child
sequences keyed by (k, 0) and (k, 1, j). Shards are therefore independent of
each other and of how many run, and a scan does not depend on how many scans
come after it.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator

import numpy as np

from omnilidar.data.synthetic.render import render_scan
from omnilidar.data.synthetic.scene import Scene, generate_scene
from omnilidar.data.synthetic.trajectory import route_poses
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import get_sensor


def _stable_hash(text: str) -> int:
    return zlib.crc32(text.encode("utf-8"))


def shard_entropy(root_seed: int, dataset: str, shard: str) -> list[int]:
    """Entropy of one shard's seed sequence (stable across Python runs)."""
    return [int(root_seed), _stable_hash(dataset), _stable_hash(str(shard))]


def scene_rng(entropy: list[int], scene: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(entropy, spawn_key=(scene, 0)))


def scan_rng(entropy: list[int], scene: int, scan: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(entropy, spawn_key=(scene, 1, scan)))


def simulate_sequence(settings: dict, entropy: list[int], scene_index: int, sensor_name: str, platform: str,
                      num_scans: int, spacing_m: float) -> tuple[Scene, Iterator[Scan]]:
    """Generate scene ``scene_index`` of a shard and lazily render ``num_scans``
    scans of ``platform`` with sensor preset ``sensor_name`` along its route.

    ``settings`` is the validated ``synthetic`` section.
    """
    sensor = get_sensor(sensor_name)
    rng = scene_rng(entropy, scene_index)
    scene = generate_scene(rng, settings["world"], max(num_scans - 1, 0) * spacing_m)
    poses = route_poses(scene, platform, sensor, num_scans, spacing_m, rng)

    def scans() -> Iterator[Scan]:
        for j, pose in enumerate(poses):
            yield render_scan(scene, sensor, pose, scan_rng(entropy, scene_index, j), settings["radiometry"],
                              point_order=settings["point_order"], min_box_points=settings["min_box_points"])

    return scene, scans()
