"""Ground estimation on every platform: synthetic ray-cast scenes (vehicle, drone,
quadruped) against their labels, and sanity on real KITTI scans."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ground_scenes import make_scene, platform_sensors, tilted
from omnilidar.errors import InputError
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import PRESETS
from omnilidar.domains.ground import (
    estimate_ground,
    fit_plane_normal,
    ground_truth_mask,
    level,
    mask_scores,
    up_vector,
)

from real_samples import real_file
PLATFORMS = platform_sensors()


@pytest.fixture(scope="module")
def scenes():
    out = {}
    for name, sensor in PLATFORMS.items():
        for k, slope in enumerate([(0.0, 0.0), (4.0, -2.0)]):
            out[name, slope] = make_scene(sensor, np.random.default_rng(10 + k), slope_deg=slope)
    return out


@pytest.mark.parametrize("platform", list(PLATFORMS))
@pytest.mark.parametrize("slope", [(0.0, 0.0), (4.0, -2.0)])
def test_precision_recall_on_synthetic_scenes(scenes, platform, slope):
    scan = scenes[platform, slope]
    truth = ground_truth_mask(scan.semantic)
    assert 0.2 < truth.mean() < 0.8  # the scene has both ground and objects
    scores = mask_scores(estimate_ground(scan, PLATFORMS[platform]), truth)
    assert scores["precision"] >= 0.9, scores
    assert scores["recall"] >= 0.9, scores


@pytest.mark.parametrize("platform", list(PLATFORMS))
def test_robust_to_pose_errors(scenes, platform):
    """A 3 deg pitch error or a mount height off by 2x still finds the ground
    (the plane fit absorbs tilt; the fallback search finds the height)."""
    scan = scenes[platform, (0.0, 0.0)]
    truth = ground_truth_mask(scan.semantic)
    sensor = PLATFORMS[platform]
    for wrong in (tilted(sensor, 3.0), tilted(sensor, -3.0),
                  replace(sensor, mount_height=sensor.mount_height * 2.0),
                  replace(sensor, mount_height=sensor.mount_height * 0.4)):
        scores = mask_scores(estimate_ground(scan, wrong), truth)
        assert scores["precision"] >= 0.9 and scores["recall"] >= 0.9, (wrong, scores)


def test_levelled_clouds_are_recognised(scenes):
    """A drone cloud stored already levelled (pitch undone, as the synthetic
    world writes it) is handled with the pitched sensor preset."""
    sensor = PLATFORMS["drone"]
    scan = scenes["drone", (0.0, 0.0)]
    pts = scan.points.copy()
    pts[:, :3] = level(scan.xyz, sensor)
    scores = mask_scores(estimate_ground(scan.with_points(pts), sensor), ground_truth_mask(scan.semantic))
    assert scores["precision"] >= 0.9 and scores["recall"] >= 0.9, scores


def test_synthetic_world_every_platform():
    """One rendered scan per platform of the synthetic world (when available)."""
    try:
        from omnilidar.config import section_defaults
        from omnilidar.data.synthetic import render, scene, trajectory

        settings = section_defaults("synthetic")
        world, radiometry = settings["world"], settings["radiometry"]
    except (ImportError, KeyError, InputError) as err:  # the world is optional here
        pytest.skip(f"synthetic world unavailable: {err}")
    rng = np.random.default_rng(0)
    world_scene = scene.generate_scene(rng, world, 40.0)
    for platform, sensor in PLATFORMS.items():
        pose = trajectory.route_poses(world_scene, platform, sensor, 1, 20.0, rng)[0]
        scan = render.render_scan(world_scene, sensor, pose, rng, radiometry)
        scores = mask_scores(estimate_ground(scan, sensor), ground_truth_mask(scan.semantic))
        assert scores["precision"] >= 0.9 and scores["recall"] >= 0.9, (platform, scores)


def test_objects_on_the_ground_are_not_ground(scenes):
    scan = scenes["vehicle", (0.0, 0.0)]
    mask = estimate_ground(scan, PLATFORMS["vehicle"])
    for lab in (10, 30, 80):  # car, person, pole: at most their feet
        sel = scan.semantic == lab
        if sel.any():
            assert mask[sel].mean() < 0.2, lab


def test_level_and_up_vector_agree():
    for sensor in PLATFORMS.values():
        up = up_vector(sensor)
        np.testing.assert_allclose(level(up[None, :], sensor)[0], [0.0, 0.0, 1.0], atol=1e-12)
    # Drone pitched 20 deg nose-down: a beam 22.5 deg below the sensor's x axis
    # points 42.5 deg below the horizon.
    d = np.array([[np.cos(np.deg2rad(22.5)), 0.0, -np.sin(np.deg2rad(22.5))]])
    z = level(d, PRESETS["drone_os64"])[0, 2]
    assert z == pytest.approx(-np.sin(np.deg2rad(42.5)))


def test_fit_plane_normal_and_fallbacks():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-10, 10, (500, 2))
    n_true = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0])
    z = -(n_true[0] * xy[:, 0] + n_true[1] * xy[:, 1]) / n_true[2] - 1.7
    n = fit_plane_normal(np.column_stack([xy, z]), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(n, n_true, atol=1e-9)
    prior = np.array([0.0, 0.0, 1.0])
    assert np.array_equal(fit_plane_normal(np.zeros((2, 3)), prior), prior)  # too few points
    line = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])
    assert np.array_equal(fit_plane_normal(line, prior), prior)  # collinear


def test_edge_cases():
    sensor = PRESETS["kitti_hdl64e"]
    assert estimate_ground(Scan(np.zeros((0, 4), np.float32)), sensor).shape == (0,)
    one = estimate_ground(Scan(np.array([[5.0, 0.0, -1.73, 0.2]], np.float32)), sensor)
    assert one.tolist() == [True]
    high = estimate_ground(Scan(np.array([[5.0, 0.0, 3.0, 0.2]], np.float32)), sensor)
    assert high.tolist() == [False]
    pts = np.array([[np.nan, 0, -1.73, 0], [0, 0, 0, 0], [1e6, 0, -1.73, 0], [3, 1, -1.72, 0]], np.float32)
    mask = estimate_ground(Scan(pts), sensor)
    assert mask.dtype == bool and mask.shape == (4,)
    assert not mask[0] and not mask[1]  # NaN and the sensor origin are not ground
    assert mask[3]


def test_deterministic(scenes):
    scan = scenes["drone", (0.0, 0.0)]
    a = estimate_ground(scan, PLATFORMS["drone"], np.random.default_rng(0))
    b = estimate_ground(scan, PLATFORMS["drone"], np.random.default_rng(1))
    assert np.array_equal(a, b)


def test_mask_scores():
    s = mask_scores(np.array([1, 1, 0, 0], bool), np.array([1, 0, 1, 0], bool))
    assert s == {"precision": 0.5, "recall": 0.5, "iou": pytest.approx(1 / 3)}
    assert mask_scores(np.zeros(3, bool), np.zeros(3, bool))["iou"] == 1.0


@pytest.mark.parametrize("name", ["kitti_object/velodyne/000000.bin", "kitti_object/velodyne/000001.bin"])
def test_real_kitti_ground_is_a_plane_near_the_mount_height(name):
    path = real_file(name)
    pts = np.fromfile(path, np.float32).reshape(-1, 4)
    mask = estimate_ground(Scan(pts), PRESETS["kitti_hdl64e"])
    assert 0.3 < mask.mean() < 0.8
    g = pts[mask, :3].astype(np.float64)
    near = np.hypot(g[:, 0], g[:, 1]) < 20
    A = np.column_stack([g[near, 0], g[near, 1], np.ones(near.sum())])
    (a, b, c), *_ = np.linalg.lstsq(A, g[near, 2], rcond=None)
    assert c == pytest.approx(-1.73, abs=0.15)
    within = np.abs(g[:, 2] - (a * g[:, 0] + b * g[:, 1] + c)) < 0.2
    assert within[near].mean() > 0.9
