"""Dataset readers and writers on the real samples, and write/read round trips (on synthetic sweeps)."""

from __future__ import annotations

import numpy as np
import pytest

from omnilidar.io import kitti360, kitti_object, nuscenes, pi3det, semantickitti
from omnilidar.geometry.boxes import box_corners, points_in_boxes
from omnilidar.lidar.scan import Boxes, Scan
from real_samples import NUSCENES_SWEEP, SEMANTICKITTI_SCAN, SEMANTICKITTI_TINY, real_file, require_real

KITTI_COUNTS = {"000000": 115_384, "000001": 120_268}


# ------------------------------------------------------------------ KITTI scans


@pytest.mark.parametrize("frame", sorted(KITTI_COUNTS))
def test_kitti_object_scans(frame):
    scan = semantickitti.read_scan(real_file(f"kitti_object/velodyne/{frame}.bin"))
    assert len(scan) == KITTI_COUNTS[frame]
    assert scan.points.dtype == np.float32 and scan.intensity_scale == 1.0
    assert scan.intensity.min() == 0.0 and 0.9 < scan.intensity.max() <= 1.0
    zeros = np.mean(scan.intensity == 0)
    assert 0.07 < zeros < 0.12  # KITTI: ~8-10 % exact zeros
    # Exact zeros are mostly far returns.
    far = np.linalg.norm(scan.xyz, axis=1) > 50
    assert np.mean(far[scan.intensity == 0]) > np.mean(far)
    assert scan.semantic is None and scan.ring is None


def test_semantickitti_sequence_without_labels():
    pairs = semantickitti.sequence_paths(require_real(SEMANTICKITTI_SCAN) / "semantickitti", "00")
    assert [(p.name, lab) for p, lab in pairs] == [("000000.bin", None)]
    scan = semantickitti.read_scan(pairs[0][0])
    assert len(scan) == 124_668
    assert 0.0 <= scan.intensity.min() and scan.intensity.max() <= 1.0
    assert 0.07 < np.mean(scan.intensity == 0) < 0.12


def test_semantickitti_tiny_label_decoding():
    pairs = semantickitti.sequence_paths(require_real(SEMANTICKITTI_TINY) / "semantickitti_tiny", 0)  # int accepted
    assert len(pairs) == 1
    bin_path, label_path = pairs[0]
    assert label_path is not None and label_path.name == "000000.label"
    scan = semantickitti.read_scan(bin_path, label_path)
    assert len(scan) == 50
    raw = np.fromfile(label_path, dtype="<u4")
    np.testing.assert_array_equal(scan.semantic, raw & 0xFFFF)
    np.testing.assert_array_equal(scan.instance, raw >> 16)
    np.testing.assert_array_equal(scan.label, raw)
    assert set(np.unique(scan.semantic).tolist()) <= set(semantickitti.LEARNING_MAP)
    train = semantickitti.to_train_ids(scan.semantic)
    assert train.dtype == np.uint8 and train.max() <= 19
    assert (train[scan.semantic == 50] == 13).all()  # building


def test_learning_map_round_trip():
    lm, inv = semantickitti.LEARNING_MAP, semantickitti.LEARNING_MAP_INV
    assert len(semantickitti.CLASS_NAMES) == 19
    assert set(lm.values()) == set(range(20)) and set(inv) == set(range(20))
    raw = np.array(sorted(lm), dtype=np.uint16)
    np.testing.assert_array_equal(semantickitti.to_train_ids(raw), [lm[r] for r in raw.tolist()])
    # train -> raw -> train is the identity; raw -> train -> raw -> train is stable.
    ids = np.arange(20, dtype=np.uint8)
    np.testing.assert_array_equal(semantickitti.to_train_ids(semantickitti.to_raw_ids(ids)), ids)
    once = semantickitti.to_train_ids(raw)
    np.testing.assert_array_equal(semantickitti.to_train_ids(semantickitti.to_raw_ids(once)), once)
    assert semantickitti.to_raw_ids(np.array([1, 9]))[0] == 10 and semantickitti.to_raw_ids([9])[0] == 40
    # Official map details that spvnas-style maps get wrong.
    assert lm[13] == 5 and lm[16] == 5 and lm[60] == 9 and lm[252] == 1
    # Unknown raw ids are ignored (0).
    np.testing.assert_array_equal(semantickitti.to_train_ids(np.array([2, 100, 65535])), [0, 0, 0])
    assert semantickitti.SPLITS["val"] == ["08"] and "08" not in semantickitti.SPLITS["train"]


# --------------------------------------------------------------------- nuScenes


def test_nuscenes_sample():
    raw = nuscenes.read_points(real_file(NUSCENES_SWEEP))
    assert raw.shape == (34_688, 5)
    scan = nuscenes.read_scan(real_file(NUSCENES_SWEEP))
    assert len(scan) == 34_688 and scan.intensity_scale == 255.0
    assert scan.intensity.min() >= 0 and scan.intensity.max() == 255.0
    assert scan.ring.dtype == np.int16 and scan.ring.min() == 0 and scan.ring.max() == 31
    np.testing.assert_array_equal(scan.ring, 31 - raw[:, 4].astype(np.int16))
    # Our convention: ring 0 = top beam, so median elevation falls with the ring id.
    elev = np.degrees(np.arcsin(scan.xyz[:, 2] / np.linalg.norm(scan.xyz, axis=1)))
    med = np.array([np.median(elev[scan.ring == r]) for r in range(32)])
    assert (np.diff(med) < 0).all()
    assert med[0] > 9 and med[31] < -29  # HDL-32E: +10.67 .. -30.67 deg


def test_nuscenes_round_trip(tmp_path):
    scan = nuscenes.read_scan(real_file(NUSCENES_SWEEP))
    out = tmp_path / "sweep.pcd.bin"
    nuscenes.write_scan(scan, out)
    assert out.read_bytes() == real_file(NUSCENES_SWEEP).read_bytes()  # bit-exact


def test_nuscenes_lidarseg_round_trip(synthetic_nuscenes_sweep, tmp_path):
    scan = synthetic_nuscenes_sweep
    labels = (np.arange(len(scan)) % 32).astype(np.uint8)
    nuscenes.write_lidarseg(tmp_path / "seg.bin", labels)
    np.testing.assert_array_equal(nuscenes.read_lidarseg(tmp_path / "seg.bin", len(scan)), labels)


def test_intensity_scale_conversion(synthetic_nuscenes_sweep, tmp_path):
    scan = synthetic_nuscenes_sweep
    assert scan.intensity_scale == 255.0 and scan.intensity.max() > 1.0
    semantickitti.write_scan(scan, tmp_path / "k.bin")
    kitti = semantickitti.read_scan(tmp_path / "k.bin")
    np.testing.assert_allclose(kitti.intensity, scan.intensity / 255.0, atol=1e-6)
    kitti = Scan(kitti.points, ring=scan.ring)
    nuscenes.write_scan(kitti, tmp_path / "n.pcd.bin")
    back = nuscenes.read_scan(tmp_path / "n.pcd.bin")
    np.testing.assert_allclose(back.intensity, scan.intensity, atol=1e-3)
    np.testing.assert_array_equal(back.ring, scan.ring)


# ----------------------------------------------------------------- KITTI boxes


@pytest.mark.parametrize("frame", sorted(KITTI_COUNTS))
def test_kitti_boxes_contain_points(frame):
    root = require_real(f"kitti_object/{sub}/{frame}.{ext}" for sub, ext in
                        (("velodyne", "bin"), ("label_2", "txt"), ("calib", "txt"))) / "kitti_object"
    objects = kitti_object.read_objects(root / "label_2" / f"{frame}.txt")
    calib = kitti_object.read_calib(root / "calib" / f"{frame}.txt")
    assert calib["P2"].shape == (3, 4) and calib["R0_rect"].shape == (3, 3)
    assert calib["Tr_velo_to_cam"].shape == (3, 4) and calib["Tr_imu_to_velo"].shape == (3, 4)
    boxes = kitti_object.objects_to_lidar_boxes(objects, calib)
    labelled = [o for o in objects if o.type != "DontCare"]
    assert len(boxes) == len(labelled) > 0
    scan = semantickitti.read_scan(root / "velodyne" / f"{frame}.bin")
    counts = points_in_boxes(scan.points, boxes).sum(axis=0)
    dist = np.linalg.norm(boxes.boxes[:, :2], axis=1)
    for name, d, n in zip(boxes.names, dist, counts):
        assert n >= 5, (name, d, n)
        if name in ("Car", "Pedestrian", "Cyclist") and d < 40:
            assert n >= 10, (name, d, n)
    # The lidar boxes project back onto the annotated 2D boxes (checks the frames).
    back = kitti_object.lidar_boxes_to_objects(boxes, calib, image_shape=(375, 1242))
    for orig, rt in zip(labelled, back):
        np.testing.assert_allclose(rt.location, orig.location, atol=1e-4)
        np.testing.assert_allclose(rt.dimensions, orig.dimensions, atol=1e-5)
        assert abs(np.angle(np.exp(1j * (rt.rotation_y - orig.rotation_y)))) < 1e-5
        assert abs(np.angle(np.exp(1j * (rt.alpha - orig.alpha)))) < 0.02
        np.testing.assert_allclose(rt.bbox2d, orig.bbox2d, atol=12)
    # Headings: boxes along the road (rotation_y ~ +-pi/2) point along lidar x.
    assert np.all(np.abs(np.sin(boxes.boxes[dist > 40, 6])) < 0.05)
    # A class filter keeps only the named types.
    cars = kitti_object.objects_to_lidar_boxes(objects, calib, classes=("Car",))
    assert set(cars.names.tolist()) <= {"Car"}


def test_kitti_label_and_calib_round_trip(tmp_path):
    root = require_real("kitti_object/label_2/000001.txt", "kitti_object/calib/000001.txt") / "kitti_object"
    objects = kitti_object.read_objects(root / "label_2" / "000001.txt")
    calib = kitti_object.read_calib(root / "calib" / "000001.txt")
    kitti_object.write_objects(tmp_path / "l.txt", objects)
    assert kitti_object.read_objects(tmp_path / "l.txt") == objects
    kitti_object.write_calib(tmp_path / "c.txt", calib)
    again = kitti_object.read_calib(tmp_path / "c.txt")
    assert again.keys() == calib.keys()
    for key in calib:
        np.testing.assert_array_equal(again[key], calib[key])
    boxes = kitti_object.read_boxes_lidar(tmp_path / "l.txt", tmp_path / "c.txt")
    scored = kitti_object.lidar_boxes_to_objects(boxes, calib, scores=np.array([0.9, 0.5, 0.25]))
    kitti_object.write_objects(tmp_path / "p.txt", scored)
    read = kitti_object.read_objects(tmp_path / "p.txt")
    assert [o.score for o in read] == [0.9, 0.5, 0.25]
    rt = kitti_object.objects_to_lidar_boxes(read, calib)
    np.testing.assert_allclose(rt.boxes, boxes.boxes, atol=2e-4)
    # Boxes behind the camera get no 2D box.
    behind = Boxes(np.array([[-10, 0, -1, 4, 2, 1.5, 0]]), ["Car"])
    assert kitti_object.lidar_boxes_to_objects(behind, calib)[0].bbox2d == (-1.0, -1.0, -1.0, -1.0)


# -------------------------------------------------------------------- box ops


def test_points_in_boxes_rotated():
    # 4 x 2 x 2 m box at (10, 5, 1), turned 90 deg: its length runs along y.
    box = np.array([[10, 5, 1, 4, 2, 2, np.pi / 2]], dtype=np.float32)
    pts = np.array([
        [10, 6.9, 1, 0],  # inside, along the length
        [11.9, 5, 1, 0],  # outside: beyond the half-width along x
        [10, 5, 2.1, 0],  # above
        [10.9, 3.1, 0.1, 0],  # inside near a corner
        [10, 3.0, 1, 0],  # on the end face: inside (inclusive)
    ], dtype=np.float32)
    np.testing.assert_array_equal(points_in_boxes(pts, box)[:, 0], [True, False, False, True, True])
    assert points_in_boxes(np.zeros((0, 3)), box).shape == (0, 1)
    assert points_in_boxes(pts, Boxes.empty()).shape == (5, 0)


def test_points_in_boxes_matches_corners():
    rng = np.random.default_rng(0)
    boxes = np.column_stack([
        rng.uniform(-20, 20, (30, 3)), rng.uniform(0.5, 5, (30, 3)), rng.uniform(-np.pi, np.pi, 30),
    ])
    pts = rng.uniform(-25, 25, (5000, 3))
    got = points_in_boxes(pts, boxes)
    # Independent check: express points in each box's frame with a rotation matrix.
    for m, b in enumerate(boxes):
        c, s = np.cos(b[6]), np.sin(b[6])
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        local = (pts - b[:3]) @ rot
        np.testing.assert_array_equal(got[:, m], (np.abs(local) <= b[3:6] / 2).all(axis=1))
    # Corners pulled slightly towards the centre lie inside their own box.
    corners = box_corners(boxes)
    shrunk = boxes[:, None, :3] + 0.999 * (corners - boxes[:, None, :3])
    inside = points_in_boxes(shrunk.reshape(-1, 3), boxes)
    assert inside[np.arange(240), np.repeat(np.arange(30), 8)].all()


# ----------------------------------------------------------------- round trips


def test_semantickitti_round_trip(synthetic_sweep, tmp_path):
    scan = synthetic_sweep.select(np.linspace(0, len(synthetic_sweep) - 1, 50).astype(int))  # 50 labelled points
    assert scan.semantic.any()
    scan = Scan(scan.points, scan.semantic, np.arange(50, dtype=np.uint16) * 1000)
    root = tmp_path / "sk"
    seq = root / "sequences" / "08"
    semantickitti.write_scan(scan, seq / "velodyne" / "000007.bin", seq / "labels" / "000007.label")
    semantickitti.write_scan(scan, seq / "velodyne" / "000003.bin", seq / "labels" / "000003.label")
    pairs = semantickitti.sequence_paths(root, "8")
    assert [p.stem for p, _ in pairs] == ["000003", "000007"]
    back = semantickitti.read_scan(*pairs[1])
    np.testing.assert_array_equal(back.points, scan.points)
    np.testing.assert_array_equal(back.semantic, scan.semantic)
    np.testing.assert_array_equal(back.instance, scan.instance)
    # Raw point and label writers.
    semantickitti.write_points(tmp_path / "p.bin", scan.points.astype(np.float64))
    np.testing.assert_array_equal(semantickitti.read_points(tmp_path / "p.bin"), scan.points)
    semantickitti.write_label(tmp_path / "l.label", scan.semantic, None)
    sem, inst = semantickitti.read_label(tmp_path / "l.label", 50)
    np.testing.assert_array_equal(sem, scan.semantic)
    assert not inst.any()


def test_kitti360_paths_and_round_trip(synthetic_sweep, tmp_path):
    path = kitti360.scan_path(tmp_path, 3, 42)
    assert path.relative_to(tmp_path).as_posix() == (
        "data_3d_raw/2013_05_28_drive_0003_sync/velodyne_points/data/0000000042.bin"
    )
    scan = Scan(synthetic_sweep.points)
    kitti360.write_scan(scan, kitti360.scan_path(tmp_path, 3, 42))
    kitti360.write_scan(scan.select(np.arange(100)), kitti360.scan_path(tmp_path, 3, 7))
    paths = kitti360.sequence_paths(tmp_path, 3)
    assert [p.name for p in paths] == ["0000000007.bin", "0000000042.bin"]
    back = kitti360.read_scan(paths[1])
    np.testing.assert_array_equal(back.points, scan.points)
    assert kitti360.SPLITS == {"train": [3, 4, 5, 6, 7, 9, 10], "test": [0, 2]}


def test_pi3det_round_trip(synthetic_sweep, tmp_path):
    root = tmp_path / "pi3det"
    scan = Scan(synthetic_sweep.points)
    semantickitti.write_scan(scan, root / "drone" / "000000.bin")
    boxes = Boxes(np.array([[5, 1, -1, 4, 2, 1.5, 0.3], [8, -2, -1, 0.6, 0.6, 1.7, 0]]),
                  ["Vehicle", "Pedestrian"])
    info = pi3det.make_info("000000", "Quadruped", "drone/000000.bin", boxes)
    assert info["point_clout_path"] == "drone/000000.bin"
    assert info["annos"]["gt_names"].tolist() == ["Car", "Pedestrian"]  # alias resolved
    assert info["annos"]["gt_boxes_lidar"].shape == (2, 7)
    empty = pi3det.make_info("000001", "Drone", "drone/000000.bin", Boxes.empty())
    pi3det.write_infos(root / "infos.pkl", [info, empty])
    infos = pi3det.read_infos(root / "infos.pkl")
    assert [i["frame_id"] for i in infos] == ["000000", "000001"]
    np.testing.assert_array_equal(infos[0]["annos"]["gt_boxes_lidar"], boxes.boxes)
    got = pi3det.read_scan(infos[0], root)
    np.testing.assert_array_equal(got.points, scan.points)
    assert got.boxes.names.tolist() == ["Car", "Pedestrian"]
    np.testing.assert_array_equal(got.boxes.boxes, boxes.boxes)
    assert len(pi3det.read_scan(infos[1], root).boxes) == 0
