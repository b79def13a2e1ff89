"""Detection data pipeline: Pi3DET platform config, voxelization, augmentation, frames, collate,
subsets and pseudo-box shards (no detector needed)."""

from __future__ import annotations

import numpy as np
import pytest

from omnilidar.config import validate
from omnilidar.downstream.det.augment import augment, limit_heading, rotate_about_z, rotate_objects
from omnilidar.downstream.det.data_config import anchor_generator_config, platform_config
from omnilidar.downstream.det.dataset import DetCollate, DetScanDataset
from omnilidar.downstream.det.voxelize import points_to_voxels
from omnilidar.errors import InputError
from omnilidar.io import pi3det, semantickitti
from omnilidar.lidar.scan import Boxes, Scan


def det_section(**over) -> dict:
    return validate({"det": over}, "downstream.schema.yaml")["det"]


def brute_force_voxels(points, voxel_size, pcr, max_points, max_voxels):
    """Point by point, as spconv's point-to-voxel does."""
    lo, vs = np.asarray(pcr[:3], np.float32), np.asarray(voxel_size, np.float32)
    grid = np.round((np.asarray(pcr[3:], np.float32) - lo) / vs).astype(int)
    slots: dict[tuple, int] = {}
    voxels, coords, counts = [], [], []
    for p in points:
        c = np.floor((p[:3] - lo) / vs).astype(int)
        if (c < 0).any() or (c >= grid).any():
            continue
        key = tuple(c[::-1])
        if key not in slots:
            if len(slots) >= max_voxels:
                continue
            slots[key] = len(slots)
            voxels.append(np.zeros((max_points, points.shape[1]), np.float32))
            coords.append(key)
            counts.append(0)
        v = slots[key]
        if counts[v] < max_points:
            voxels[v][counts[v]] = p
            counts[v] += 1
    return np.array(voxels).reshape(-1, max_points, points.shape[1]), np.array(coords).reshape(-1, 3), np.array(counts)


@pytest.mark.parametrize("max_points,max_voxels", [(5, 1000), (2, 7), (1, 3)])
def test_voxelization_matches_point_by_point_reference(max_points, max_voxels):
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(-1, 5, (300, 3)), rng.uniform(0, 1, (300, 1))], axis=1).astype(np.float32)
    pts[::7, :3] = pts[0, :3]  # a crowded voxel
    pcr, vs = [0, 0, 0, 4, 4, 2], [0.5, 0.5, 0.5]
    got = points_to_voxels(pts, vs, pcr, max_points, max_voxels)
    want = brute_force_voxels(pts, vs, pcr, max_points, max_voxels)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    assert got[1].dtype == np.int32 and got[2].max() <= max_points and len(got[0]) <= max_voxels


def test_voxelization_of_no_point_in_range_is_empty():
    v, c, n = points_to_voxels(np.full((4, 4), -9, np.float32), [1, 1, 1], [0, 0, 0, 8, 8, 8], 5, 10)
    assert v.shape == (0, 5, 4) and c.shape == (0, 3) and n.shape == (0,)


def test_platform_config_classes_shift_and_anchors():
    det = det_section()
    drone, quad = platform_config(det, "drone"), platform_config(det, "quadruped")
    assert drone.class_names == ("Car",) and quad.class_names == ("Car", "Pedestrian")
    assert drone.shift[2] > 5 and quad.shift[2] < 0  # ground moved to about -1.7 m for both
    assert list(drone.grid_size) == [752, 1504, 40]
    anchors = anchor_generator_config(quad)
    assert [a["class_name"] for a in anchors] == ["Car", "Pedestrian"]
    assert anchors[1]["anchor_sizes"] == [[0.8, 0.6, 1.73]] and anchors[0]["matched_threshold"] == 0.6
    coarse = platform_config(det_section(voxel_size=[0.2, 0.2, 0.15]), "drone")
    assert list(coarse.grid_size) == [376, 752, 40]


def test_platform_config_rejects_bad_settings():
    with pytest.raises(InputError, match="not annotated on Drone"):
        platform_config(det_section(platforms={"drone": {"classes": ["Pedestrian"]}}), "drone")
    with pytest.raises(InputError, match="does not divide"):
        platform_config(det_section(voxel_size=[0.33, 0.2, 0.15]), "drone")


def test_augmentations_move_points_and_boxes_together():
    rng = np.random.default_rng(1)
    boxes = np.array([[10, 3, -1, 4, 2, 1.5, 0.3], [20, -5, -1, 1, 1, 2, -2.0]], np.float32)
    # Points inside each box in its own frame.
    local = rng.uniform(-0.45, 0.45, (200, 3)).astype(np.float32)
    pts = np.concatenate([box_points(b, local) for b in boxes])
    settings = {"object_rotation": {"probability": 0.8, "range": [-0.4, 0.4]}, "flip_x": True,
                "rotation": [-0.8, 0.8], "scaling": [0.9, 1.1]}
    for seed in range(6):
        p2, b2 = augment(pts, boxes, settings, np.random.default_rng(seed))
        for k, b in enumerate(b2):
            d = p2[k * 200:(k + 1) * 200, :3] - b[:3]
            c, s = np.cos(-b[6]), np.sin(-b[6])
            x, y = d[:, 0] * c - d[:, 1] * s, d[:, 0] * s + d[:, 1] * c
            assert (np.abs(x) <= b[3] / 2 + 1e-4).all() and (np.abs(y) <= b[4] / 2 + 1e-4).all()
            assert (np.abs(d[:, 2]) <= b[5] / 2 + 1e-4).all()
    p3, b3 = rotate_about_z(pts, boxes, np.pi / 2)
    np.testing.assert_allclose(b3[0, :2], [-3, 10], atol=1e-5)
    np.testing.assert_allclose(limit_heading(np.array([np.pi, -np.pi, 3 * np.pi / 2])), [-np.pi, -np.pi, -np.pi / 2])


def box_points(box, local):
    """Points at box-frame offsets ``local`` (fractions of the size) of one lidar box."""
    c, s = np.cos(box[6]), np.sin(box[6])
    xyz = local * box[3:6]
    return np.stack([xyz[:, 0] * c - xyz[:, 1] * s + box[0], xyz[:, 0] * s + xyz[:, 1] * c + box[1],
                     xyz[:, 2] + box[2], np.ones(len(xyz))], 1).astype(np.float32)


def test_object_rotation_turns_free_boxes_with_their_points_and_clears_their_new_footprint():
    rng = np.random.default_rng(3)
    free = np.array([10, 0, -1, 4, 1, 1.5, 0], np.float32)  # long and thin: turning sweeps new ground
    # Two boxes side by side with 0.1 m between them: almost every turn of either hits the other.
    tight = np.array([[30, 0, -1, 4, 2, 1.5, 0], [30, 2.1, -1, 4, 2, 1.5, 0]], np.float32)
    boxes = np.concatenate([free[None], tight])
    own = box_points(free, rng.uniform(-0.45, 0.45, (300, 3)))
    # Background points on the ground around the free box (outside it now).
    ground = np.stack([rng.uniform(7, 13, 2000), rng.uniform(-2, 2, 2000), np.full(2000, -1.0),
                       np.zeros(2000)], 1).astype(np.float32)
    ground = ground[(np.abs(ground[:, 0] - 10) > 2.05) | (np.abs(ground[:, 1]) > 0.55)]
    tight_pts = np.concatenate([box_points(b, rng.uniform(-0.45, 0.45, (100, 3))) for b in tight])
    points = np.concatenate([own, ground, tight_pts])
    p2, b2 = rotate_objects(points, boxes, 1.0, (0.3, 0.38), np.random.default_rng(0))
    turn = b2[0, 6] - boxes[0, 6]
    assert 0.3 <= turn <= 0.38
    np.testing.assert_array_equal(b2[0, :6], boxes[0, :6])
    np.testing.assert_array_equal(b2[1:], tight)  # every try collides: untouched
    # The box's own points turned with it (all still inside, by intensity 1), none left behind.
    from omnilidar.downstream.det.augment import _inside
    inside_new = _inside(p2, b2[0])
    assert int(np.sum(p2[inside_new, 3] == 1)) == 300 and not np.any(p2[inside_new, 3] == 0)
    # Ground points the turned box now covers were dropped, the others kept.
    assert len(p2) < len(points) and len(p2) > len(points) - 400
    # Same generator, same result; probability 0 changes nothing.
    p3, b3 = rotate_objects(points, boxes, 1.0, (0.3, 0.38), np.random.default_rng(0))
    np.testing.assert_array_equal(p2, p3) and np.testing.assert_array_equal(b2, b3)
    p4, b4 = rotate_objects(points, boxes, 0.0, (0.3, 0.38), np.random.default_rng(0))
    np.testing.assert_array_equal(p4, points) and np.testing.assert_array_equal(b4, boxes)


def write_platform(root, platform_name, frames):
    """A tiny Pi3DET platform: frames = [(points, boxes, names)]; returns its info list."""
    folder = root / platform_name.lower()
    (folder / "velodyne").mkdir(parents=True)
    infos = []
    for k, (points, boxes, names) in enumerate(frames):
        fid = f"{k:06d}"
        semantickitti.write_scan(Scan(points=points.astype(np.float32)), folder / "velodyne" / f"{fid}.bin", None)
        infos.append(pi3det.make_info(fid, platform_name, f"{platform_name.lower()}/velodyne/{fid}.bin",
                                      Boxes(np.asarray(boxes, np.float32).reshape(-1, 7), names)))
    return infos


def test_frames_are_shifted_filtered_and_collated(tmp_path):
    from omnilidar.downstream.det.dataset import records_from_infos

    rng = np.random.default_rng(2)
    pts = np.concatenate([rng.uniform(-20, 60, (500, 2)), rng.uniform(-1.5, 1.5, (500, 1)),
                          rng.uniform(0, 1, (500, 1))], 1)
    frames = [(pts, [[15, 2, -0.5, 4, 2, 1.5, 0.1], [-10, 0, -0.5, 4, 2, 1.5, 0], [8, 1, -0.8, 0.8, 0.6, 1.7, 0]],
               ["Car", "Car", "Pedestrian"]),
              (pts[:100], [[30, -4, -0.5, 4, 2, 1.5, 1.0]], ["Car"])]
    infos = write_platform(tmp_path, "Quadruped", frames)
    det = det_section()
    cfg = platform_config(det, "quadruped")
    records = records_from_infos(infos, tmp_path)
    ds = DetScanDataset(records, cfg, det["voxels"])
    item = ds[0]
    # Shift added, the box behind the sensor (x < 0) dropped, class ids 1 (Car) and 2 (Pedestrian).
    np.testing.assert_allclose(item["gt_boxes"][:, 2], [-0.5 - 1.08, -0.8 - 1.08], atol=1e-5)
    assert item["gt_boxes"][:, 7].tolist() == [1.0, 2.0]
    assert (item["points"][:, 0] >= 0).all() and len(item["points"]) < 500
    batch = DetCollate()([ds[0], ds[1]])
    assert batch["batch_size"] == 2 and batch["gt_boxes"].shape == (2, 2, 8)
    assert batch["gt_boxes"][1, 1].abs().sum() == 0  # padding row
    assert batch["points"].shape[1] == 5 and set(batch["points"][:, 0].tolist()) == {0.0, 1.0}
    assert batch["voxel_coords"].shape[1] == 4 and int(batch["voxel_num_points"].sum()) <= len(batch["points"])
    # Drone frames keep only cars.
    drone = DetScanDataset(records, platform_config(det, "drone"), det["voxels"])
    assert drone.frame(0)[2].tolist() == [1, 1]


def test_training_draws_are_seeded_and_skip_frames_without_boxes(tmp_path):
    from omnilidar.downstream.det.dataset import records_from_infos

    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.uniform(0, 40, (400, 2)), rng.uniform(-10, -8, (400, 1)), rng.uniform(0, 1, (400, 1))], 1)
    frames = [(pts, np.zeros((0, 7)), []), (pts, [[15, 2, -9, 4, 2, 1.5, 0.1]], ["Car"])]
    det = det_section()
    cfg = platform_config(det, "drone")
    records = records_from_infos(write_platform(tmp_path, "Drone", frames), tmp_path)
    ds = DetScanDataset(records, cfg, det["voxels"], det["augmentation"], seed=5)
    a, b = ds[(3, 0)], ds[(3, 0)]
    assert a["index"] == 1  # frame 0 has no box: the next frame that has one is taken
    np.testing.assert_array_equal(a["points"], b["points"])
    assert not np.array_equal(ds[(4, 0)]["points"], a["points"])
    empty = DetScanDataset(records[:1], cfg, det["voxels"], det["augmentation"], seed=5)
    with pytest.raises(InputError, match="nothing to train on"):
        empty[(0, 0)]


def test_pseudo_box_shard_round_trip(tmp_path):
    from omnilidar.downstream.det.pseudo_boxes import generated_records, write_shard

    shard = tmp_path / "samples" / "Drone" / "shard_0"
    (shard / "velodyne").mkdir(parents=True)
    for name, n in (("000000", 50), ("000001", 0)):
        np.zeros((n, 4), np.float32).tofile(shard / "velodyne" / f"{name}.bin")
    preds = {"000000": {"boxes": np.array([[10, 0, -9, 4, 2, 1.5, 0], [12, 3, -9, 4, 2, 1.5, 0]], np.float32),
                        "scores": np.array([0.9, 0.1]), "names": ["Car", "Car"]}}
    out = tmp_path / "pseudo" / "Drone" / "shard_0"
    side = write_shard(shard, "Drone", preds, 0.3, out, {"detector": "voxel_rcnn"}, 1.0)
    assert side["boxes"] == {"Car": 1} and side["scans"] == 2
    infos = pi3det.read_infos(out / "infos.pkl")
    assert [i["frame_id"] for i in infos] == ["000000", "000001"] and len(infos[1]["annos"]["gt_names"]) == 0
    records, empty = generated_records([shard], [out])
    assert empty == 1 and len(records) == 1 and records[0]["names"] == ["Car"]
    np.testing.assert_allclose(records[0]["boxes"][0][:3], [10, 0, -9])
    (shard / "velodyne" / "000002.bin").write_bytes(b"")
    with pytest.raises(InputError, match="does not match sample shard"):
        generated_records([shard], [out])


def test_subsets_of_a_platform_and_frames_without_boxes(tmp_path):
    from omnilidar.data.index import build_index, write_index
    from omnilidar.downstream.det.subsets import make_det_subset

    rng = np.random.default_rng(4)
    pts = np.concatenate([rng.uniform(0, 40, (100, 2)), rng.uniform(-10, -8, (100, 1)), rng.uniform(0, 1, (100, 1))], 1)
    frames = [(pts, [[15, 2, -9, 4, 2, 1.5, 0.1]] if k == 4 else np.zeros((0, 7)), ["Car"] if k == 4 else [])
              for k in range(10)]
    infos = write_platform(tmp_path, "Drone", frames)
    pi3det.write_infos(tmp_path / "drone" / "drone_infos_train.pkl", infos)
    write_index(build_index("pi3det", tmp_path), tmp_path / "index.json")
    sub = make_det_subset(tmp_path / "index.json", "drone", 0.5)
    assert sub["every"] == 2 and sub["num_scans"] == 5 and sub["num_boxes"] == 1
    full = make_det_subset(tmp_path / "index.json", "drone", 1.0)
    assert full["num_scans"] == 10 and full["num_boxes"] == 1
    with pytest.raises(InputError, match="holds no Car box"):
        make_det_subset(tmp_path / "index.json", "drone", 0.2)


def test_cli_refuses_a_subset_without_boxes_in_one_line(tmp_path):
    import json
    import subprocess
    import sys

    from omnilidar.data.index import build_index, write_index

    rng = np.random.default_rng(5)
    pts = np.concatenate([rng.uniform(0, 40, (100, 2)), rng.uniform(-10, -8, (100, 1)), rng.uniform(0, 1, (100, 1))], 1)
    infos = write_platform(tmp_path, "Drone", [(pts, np.zeros((0, 7)), [])] * 3)
    pi3det.write_infos(tmp_path / "drone" / "drone_infos_train.pkl", infos)
    write_index(build_index("pi3det", tmp_path), tmp_path / "index.json")
    out = tmp_path / "run.pt"
    res = subprocess.run([sys.executable, "-m", "omnilidar.cli", "train-detector", "--detector", "voxel_rcnn",
                          "--platform", "drone", "--index", str(tmp_path / "index.json"), "--percent", "100",
                          "--settings", json.dumps({}), "--out", str(out)], capture_output=True, text=True)
    assert res.returncode == 2 and not out.exists()
    lines = [line for line in res.stderr.splitlines() if line.strip() and not line.startswith("$ omnilidar")]
    assert len(lines) == 1 and "index.json" in lines[0] and "holds no Car box" in lines[0]


def test_synthetic_pi3det_boxes_hold_points_and_scans_hold_objects(tmp_path):
    """The embedded default's Pi3DET sets are fit for AP: every labelled box holds points and
    the frames carry several objects (checked on a small shard of the default world)."""
    import torch

    from omnilidar.data.synthetic.export import write_shard
    from omnilidar.geometry.points_in_boxes import points_in_boxes_mask

    settings = validate({"datasets": {"pi3det": {"platforms": {"quadruped": {"scenes": 1, "scans_per_scene": 3},
                                                                "drone": {"scenes": 1, "scans_per_scene": 3}}}}},
                        "synthetic.schema.yaml")
    for platform in ("drone", "quadruped"):
        write_shard("pi3det", platform, settings, 0, tmp_path / platform)
        infos = pi3det.read_infos(tmp_path / platform / f"{platform}_infos_train.pkl")
        assert infos
        for info in infos:
            scan = pi3det.read_scan(info, tmp_path)
            boxes = scan.boxes.boxes
            assert len(boxes) >= 3, f"{platform} frame {info['frame_id']} holds {len(boxes)} boxes"
            inside = points_in_boxes_mask(torch.from_numpy(scan.points[:, :3]), torch.from_numpy(boxes)).sum(0)
            assert int(inside.min()) >= 1, f"{platform} frame {info['frame_id']}: a box holds no point"


def test_box_labeler_imports_an_openpcdet_checkpoint_weights_only(tmp_path):
    import torch

    from omnilidar.downstream.det.checkpoints import load_payload
    from omnilidar.downstream.det.labeler import import_labeler
    from omnilidar.downstream.det.model_config import build, model_config

    det = det_section()
    yaml_path = "config/detectors/voxel_rcnn.yaml"

    def openpcdet_checkpoint(platform, path):
        cfg = platform_config(det, platform)
        state = build(model_config(det, "voxel_rcnn", cfg, yaml_path), cfg).state_dict()
        torch.save({"model_state": state, "optimizer_state": {}, "epoch": 80, "it": 1000}, path)
        return state

    state = openpcdet_checkpoint("drone", tmp_path / "drone.pth")
    import_labeler(det, "voxel_rcnn", "drone", yaml_path, tmp_path / "drone.pth", tmp_path / "labeler.pt")
    payload = load_payload(tmp_path / "labeler.pt")
    assert payload["train"]["imported_from"].endswith("drone.pth")
    assert all(torch.equal(payload["model_state"][k], v) for k, v in state.items())
    # A Quadruped (Car, Pedestrian) checkpoint does not fit the Drone (Car) labeler: one clear error.
    openpcdet_checkpoint("quadruped", tmp_path / "quad.pth")
    with pytest.raises(InputError, match="quad.pth.*expects"):
        import_labeler(det, "voxel_rcnn", "drone", yaml_path, tmp_path / "quad.pth", tmp_path / "bad.pt")
    assert not (tmp_path / "bad.pt").exists()
