"""Shared test fixtures: paths of the project and of the real LiDAR samples, and the
synthetic full sweeps that tests needing "some real-sized scan" use instead."""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

from real_samples import ALL_SAMPLES, ROOT, require_real


def pytest_configure(config):
    """Under xdist, each worker's torch gets its share of the cores: more OpenMP threads than
    free cores stall at every barrier (the tiny models of the tests ran up to a fifth slower)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        import torch

        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        torch.set_num_threads(max(1, cores // workers))


def pytest_collection_modifyitems(config, items):
    """Real workflow runs (marked slow) first, in their files' order: under xdist the long ones
    then overlap each other and short tests fill the end, instead of one running alone last."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.fixture(scope="session")
def project_root() -> Path:
    return ROOT


@pytest.fixture(scope="session")
def real_data() -> Path:
    """The real LiDAR samples (OMNILIDAR_REAL_DATA); skips the test unless every sample file is there.
    Tests that read one or two files say which: require_real(...) or real_file(...)."""
    return require_real(ALL_SAMPLES)


class SyntheticWorld(NamedTuple):
    settings: dict  # the synthetic section it was rendered with
    entropy: list
    scene: object
    scans: tuple  # two full KITTI HDL-64E sweeps (Scan), 6 m apart on the route


def _read_only(scan):
    """Shared across the session: a test that writes into a sweep fails instead of changing others' input."""
    for arr in (scan.points, scan.semantic, scan.instance, scan.ring, scan.boxes.boxes):
        if arr is not None:
            arr.flags.writeable = False
    return scan


@pytest.fixture(scope="session")
def synthetic_world() -> SyntheticWorld:
    """One synthetic intersection scene and two full HDL-64E sweeps along its route,
    rendered once per test session (per xdist worker)."""
    from omnilidar.config import section_defaults
    from omnilidar.data.synthetic.sequence import shard_entropy, simulate_sequence

    settings = section_defaults("synthetic")
    settings["world"]["layout_weights"] = {"straight": 0, "curve": 0, "intersection": 1, "t_junction": 0}
    entropy = shard_entropy(7, "test", "world")
    scene, scans = simulate_sequence(settings, entropy, 0, "kitti_hdl64e", "vehicle", 2, 6.0)
    return SyntheticWorld(settings, entropy, scene, tuple(_read_only(s) for s in scans))


@pytest.fixture(scope="session")
def synthetic_sweeps(synthetic_world) -> tuple:
    """Two full synthetic KITTI HDL-64E sweeps (about 127k points each, labels, rings, boxes)."""
    return synthetic_world.scans


@pytest.fixture(scope="session")
def synthetic_sweep(synthetic_sweeps):
    """One full synthetic KITTI HDL-64E sweep."""
    return synthetic_sweeps[0]


@pytest.fixture(scope="session")
def synthetic_nuscenes_sweep(synthetic_world):
    """A full synthetic nuScenes HDL-32E sweep (intensity 0..255, rings) in the same scene."""
    from omnilidar.data.synthetic.render import render_scan
    from omnilidar.data.synthetic.trajectory import route_poses
    from omnilidar.lidar.sensors import PRESETS

    world, sensor = synthetic_world, PRESETS["nuscenes_hdl32e"]
    rng = np.random.default_rng(32)
    pose = route_poses(world.scene, "vehicle", sensor, 1, 1.0, rng)[0]
    return _read_only(render_scan(world.scene, sensor, pose, rng, world.settings["radiometry"]))


@pytest.fixture(autouse=True)
def _grad_mode_is_not_left_switched_off():
    """Stages run in-process in tests: none may leave autograd switched off globally."""
    yield
    import sys

    torch = sys.modules.get("torch")
    if torch is not None:
        assert torch.is_grad_enabled(), "a stage left torch.set_grad_enabled(False) behind"
