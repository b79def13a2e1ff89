"""Bad input to the dataset readers and writers: one InputError naming the file
and the problem, and no half-written output."""

from __future__ import annotations

import os
import pickle
import re

import numpy as np
import pytest

from omnilidar.errors import InputError
from omnilidar.io import kitti360, kitti_object, nuscenes, pi3det, pointfile, semantickitti
from omnilidar.lidar.scan import Boxes, Scan

GOOD_LABEL = "Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57\n"
GOOD_CALIB = (
    "P2: 700 0 600 45 0 700 180 0 0 0 1 0.005\n"
    "R0_rect: 1 0 0 0 1 0 0 0 1\n"
    "Tr_velo_to_cam: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27\n"
)


def points(n: int = 10) -> np.ndarray:
    rng = np.random.default_rng(1)
    pts = rng.uniform(-20, 20, (n, 4)).astype(np.float32)
    pts[:, 3] = rng.uniform(0, 1, n)
    return pts


def raises(path, *fragments):
    """Expect an InputError whose message names ``path`` and holds each fragment."""
    ctx = pytest.raises(InputError)

    class _Check:
        def __enter__(self):
            self.info = ctx.__enter__()
            return self.info

        def __exit__(self, *exc):
            handled = ctx.__exit__(*exc)
            msg = str(self.info.value)
            assert str(path) in msg, msg
            for f in fragments:
                assert f in msg, msg
            assert "\n" not in msg
            return handled

    return _Check()


# ----------------------------------------------------------------- .bin sizes


def test_bin_size_not_multiple_of_16(tmp_path):
    path = tmp_path / "bad.bin"
    path.write_bytes(points(2).tobytes() + b"\0\0")  # 34 bytes
    with raises(path, "size 34 bytes is not a multiple of 16 (float32 x,y,z,remission)"):
        semantickitti.read_points(path)
    with raises(path, "not a multiple of 16"):
        kitti360.read_scan(path)


def test_nuscenes_size_not_multiple_of_20(tmp_path):
    path = tmp_path / "bad.pcd.bin"
    path.write_bytes(np.zeros(8, np.float32).tobytes())  # 32 bytes
    with raises(path, "size 32 bytes is not a multiple of 20 (float32 x,y,z,intensity,ring)"):
        nuscenes.read_points(path)
    with raises(path, "not a multiple of 20"):
        nuscenes.read_scan(path)


# --------------------------------------------------------------------- labels


def test_label_count_differs_from_scan(tmp_path):
    semantickitti.write_points(tmp_path / "s.bin", points(10))
    semantickitti.write_label(tmp_path / "s.label", np.full(9, 40, np.uint16), np.zeros(9, np.uint16))
    with raises(tmp_path / "s.label", "has 9 labels but its scan has 10 points"):
        semantickitti.read_scan(tmp_path / "s.bin", tmp_path / "s.label")
    (tmp_path / "odd.label").write_bytes(b"\0" * 6)
    with raises(tmp_path / "odd.label", "size 6 bytes is not a multiple of 4"):
        semantickitti.read_label(tmp_path / "odd.label")


def test_lidarseg_count_and_class(tmp_path):
    nuscenes.write_lidarseg(tmp_path / "seg.bin", np.zeros(5, np.uint8))
    with raises(tmp_path / "seg.bin", "has 5 labels but its scan has 6 points"):
        nuscenes.read_lidarseg(tmp_path / "seg.bin", 6)
    (tmp_path / "hi.bin").write_bytes(bytes([1, 2, 40]))
    with raises(tmp_path / "hi.bin", "class 40"):
        nuscenes.read_lidarseg(tmp_path / "hi.bin", 3)
    with raises(tmp_path / "w.bin", "do not fit in uint8"):
        nuscenes.write_lidarseg(tmp_path / "w.bin", np.array([1, 300]))
    assert not (tmp_path / "w.bin").exists()


# -------------------------------------------------------------- NaN and range


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_coordinates(tmp_path, bad):
    pts = points(10)
    pts[[2, 7], 1] = bad
    path = tmp_path / "nan.bin"
    path.write_bytes(pts.tobytes())
    with raises(path, "2 of 10 points have NaN or infinite", "first at point 2"):
        semantickitti.read_points(path)
    nus = np.zeros((4, 5), np.float32)
    nus[3, 0] = bad
    (tmp_path / "nan.pcd.bin").write_bytes(nus.tobytes())
    with raises(tmp_path / "nan.pcd.bin", "1 of 4 points have NaN or infinite"):
        nuscenes.read_scan(tmp_path / "nan.pcd.bin")


def test_writers_refuse_nonfinite(tmp_path):
    pts = points(4).astype(np.float64)
    pts[1, 0] = np.nan
    with raises(tmp_path / "w.bin", "1 of 4 points have NaN"):
        semantickitti.write_points(tmp_path / "w.bin", pts)
    pts[1, 0] = 1e39  # finite in float64, inf in float32
    with raises(tmp_path / "w.bin", "NaN or infinite"):
        semantickitti.write_points(tmp_path / "w.bin", pts)
    assert not (tmp_path / "w.bin").exists()


def test_remission_out_of_range(tmp_path):
    # A 5-column nuScenes sweep of 4 points is 80 bytes, a whole number of KITTI
    # records: the remission check is what catches the mix-up.
    nus = np.column_stack([points(4)[:, :3], [0, 120, 255, 3], [0, 1, 2, 3]]).astype(np.float32)
    path = tmp_path / "sweep.pcd.bin"
    path.write_bytes(nus.tobytes())
    with raises(path, "remission outside 0..1"):
        semantickitti.read_scan(path)


def test_nuscenes_ring_and_intensity_checks(tmp_path):
    nus = np.column_stack([points(3)[:, :3], [1, 2, 3], [0, 31, 32]]).astype(np.float32)
    (tmp_path / "r.pcd.bin").write_bytes(nus.tobytes())
    with raises(tmp_path / "r.pcd.bin", "1 of 3 points have a ring"):
        nuscenes.read_scan(tmp_path / "r.pcd.bin")
    nus[:, 4] = [0, 1.5, 2]
    (tmp_path / "r.pcd.bin").write_bytes(nus.tobytes())
    with raises(tmp_path / "r.pcd.bin", "not an integer 0..31"):
        nuscenes.read_scan(tmp_path / "r.pcd.bin")
    nus[:, 4] = 0
    nus[0, 3] = 300
    (tmp_path / "r.pcd.bin").write_bytes(nus.tobytes())
    with raises(tmp_path / "r.pcd.bin", "intensity outside 0..255"):
        nuscenes.read_scan(tmp_path / "r.pcd.bin")
    with raises(tmp_path / "o.pcd.bin", "no ring ids"):
        nuscenes.write_scan(Scan(points(3)), tmp_path / "o.pcd.bin")
    assert not (tmp_path / "o.pcd.bin").exists()


# ---------------------------------------------------------------- empty scans


def test_empty_scan_policy(tmp_path):
    """An empty .bin is a valid raw array but never a valid sweep."""
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    assert semantickitti.read_points(empty).shape == (0, 4)
    assert nuscenes.read_points(empty).shape == (0, 5)
    for read in (semantickitti.read_scan, kitti360.read_scan, nuscenes.read_scan):
        with raises(empty, "scan has 0 points"):
            read(empty)
    with raises(tmp_path / "e.bin", "0 points"):
        semantickitti.write_scan(Scan(np.zeros((0, 4))), tmp_path / "e.bin")
    with raises(tmp_path / "e.pcd.bin", "0 points"):
        nuscenes.write_scan(Scan(np.zeros((0, 4)), ring=np.zeros(0)), tmp_path / "e.pcd.bin")
    assert not (tmp_path / "e.bin").exists() and not (tmp_path / "e.pcd.bin").exists()
    info = pi3det.make_info("0", "Drone", "empty.bin", Boxes.empty())
    with raises(empty, "scan has 0 points"):
        pi3det.read_scan(info, tmp_path)


# --------------------------------------------------------- missing files/roots


def test_missing_files_and_roots(tmp_path):
    missing = tmp_path / "nope" / "000000.bin"
    for read in (semantickitti.read_points, semantickitti.read_scan, kitti360.read_scan,
                 nuscenes.read_scan, kitti_object.read_objects, kitti_object.read_calib,
                 pi3det.read_infos):
        with raises(missing, "no such file"):
            read(missing)
    with raises(missing, "no such file"):
        semantickitti.read_label(missing, 3)
    with raises(missing, "no such file"):
        nuscenes.read_lidarseg(missing, 3)
    with raises(tmp_path / "nope", "SemanticKITTI root does not exist"):
        semantickitti.sequence_paths(tmp_path / "nope", "00")
    with raises(tmp_path / "nope", "KITTI-360 root does not exist"):
        kitti360.sequence_paths(tmp_path / "nope", 0)
    with raises(tmp_path / "sequences" / "05", "sequence folder does not exist"):
        semantickitti.sequence_paths(tmp_path, "05")
    with raises(tmp_path / "data_3d_raw", "sequence folder does not exist"):
        kitti360.sequence_paths(tmp_path, 4)
    info = pi3det.make_info("7", "Vehicle", "pts/7.bin", Boxes.empty())
    with raises(tmp_path / "nope", "Pi3DET root does not exist"):
        pi3det.read_scan(info, tmp_path / "nope")
    with raises(tmp_path / "pts" / "7.bin", "no such file"):
        pi3det.read_scan(info, tmp_path)


def test_sequence_label_mismatch(tmp_path):
    seq = tmp_path / "sequences" / "00"
    for stem in ("000000", "000001"):
        semantickitti.write_points(seq / "velodyne" / f"{stem}.bin", points(3))
    semantickitti.write_label(seq / "labels" / "000000.label", np.zeros(3, np.uint16))
    with raises(seq / "labels", "1 scans have no label (first: 000001.label)"):
        semantickitti.sequence_paths(tmp_path, "00")
    (seq / "velodyne" / "000001.bin").unlink()
    semantickitti.write_label(seq / "labels" / "000009.label", np.zeros(3, np.uint16))
    with raises(seq / "labels", "1 labels have no scan (first: 000009.label)"):
        semantickitti.sequence_paths(tmp_path, "00")
    with pytest.raises(InputError, match="sequence must be a number"):
        semantickitti.sequence_paths(tmp_path, "../00")
    with pytest.raises(InputError, match="non-negative int"):
        kitti360.scan_path(tmp_path, 3, 1.5)


# ------------------------------------------------------- malformed KITTI text


@pytest.mark.parametrize("line, problem", [
    ("Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49",
     "line 2: 14 fields, expected 15 (or 16 with a score)"),
    (GOOD_LABEL.strip() + " 0.5 7", "line 2: 17 fields"),
    ("Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 x -16.53 2.39 58.49 1.57",
     "line 2: non-numeric value"),
    ("Car 0.00 0.5 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57",
     "line 2: occluded must be an integer"),
    ("Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 -1 3.69 -16.53 2.39 58.49 1.57",
     "line 2: Car has non-positive dimensions"),
    ("Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 nan 2.39 58.49 1.57",
     "line 2: NaN or infinite"),
])
def test_malformed_label_lines(tmp_path, line, problem):
    path = tmp_path / "label.txt"
    path.write_text(GOOD_LABEL + line + "\n")
    with raises(path, problem):
        kitti_object.read_objects(path)


@pytest.mark.parametrize("text, problem", [
    (GOOD_CALIB + "P0: 1 2 3\n", "line 4: P0 has 3 values, expected 12"),
    (GOOD_CALIB.replace("R0_rect: 1 0 0 0 1 0 0 0 1", "R0_rect: 1 0 0 0 1 0 0 0"), "R0_rect has 8 values, expected 9"),
    (GOOD_CALIB + "garbage line\n", "line 4: expected 'KEY: values'"),
    (GOOD_CALIB + "P2: 1 2\n", "line 4: P2 given twice"),
    (GOOD_CALIB.replace("R0_rect", "R1_rect"), "missing R0_rect"),
    (GOOD_CALIB.replace("Tr_velo_to_cam: 0 -1 0", "Tr_velo_to_cam: 0 -2 0"), "Tr_velo_to_cam: rotation part is not"),
    (GOOD_CALIB.replace("P2: 700", "P2: seven"), "line 1: non-numeric value"),
])
def test_malformed_calib(tmp_path, text, problem):
    path = tmp_path / "calib.txt"
    path.write_text(text)
    with raises(path, problem):
        kitti_object.read_calib(path)


def test_calib_aliases_and_binary(tmp_path):
    path = tmp_path / "calib.txt"
    path.write_text(GOOD_CALIB.replace("R0_rect", "R_rect").replace("Tr_velo_to_cam", "Tr_velo_cam"))
    calib = kitti_object.read_calib(path)
    assert calib["R0_rect"].shape == (3, 3) and calib["Tr_velo_to_cam"].shape == (3, 4)
    path.write_bytes(b"\xff\xfe\x00binary")
    with raises(path, "is not a text file"):
        kitti_object.read_calib(path)


def test_kitti_writers_validate(tmp_path):
    (tmp_path / "c.txt").write_text(GOOD_CALIB)
    calib = kitti_object.read_calib(tmp_path / "c.txt")
    obj = kitti_object.KittiObject("Big Car", 0, 0, 0, (0, 0, 1, 1), (1, 1, 1), (0, 0, 5), 0)
    with raises(tmp_path / "l.txt", "one word"):
        kitti_object.write_objects(tmp_path / "l.txt", [obj])
    obj = kitti_object.KittiObject("Car", 0, 0, 0, (0, 0, 1, 1), (1, 1, float("nan")), (0, 0, 5), 0)
    with raises(tmp_path / "l.txt", "NaN or infinite"):
        kitti_object.write_objects(tmp_path / "l.txt", [obj])
    bad = dict(calib, R0_rect=np.eye(2))
    with raises(tmp_path / "c2.txt", "R0_rect has 4 values, expected 9"):
        kitti_object.write_calib(tmp_path / "c2.txt", bad)
    assert not (tmp_path / "l.txt").exists() and not (tmp_path / "c2.txt").exists()


# -------------------------------------------------------------------- pickles


def test_pickle_with_code_is_refused(tmp_path):
    marker = tmp_path / "pwned"

    class Exploit:
        def __reduce__(self):
            return (os.mkdir, (str(marker),))

    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps([Exploit()]))
    with raises(path, "unsafe or corrupt pickle", "refusing to load"):
        pi3det.read_infos(path)
    assert not marker.exists()


def _info(**over):
    info = {"frame_id": "1", "platform": "Drone", "point_clout_path": "a/1.bin",
            "annos": {"gt_names": np.array(["Car"]), "gt_boxes_lidar": np.ones((1, 7), np.float32)}}
    info.update(over)
    return info


@pytest.mark.parametrize("payload, problem", [
    ({"not": "a list"}, "must hold a list of info dicts, got dict"),
    (["text"], "info[0]: must be a dict"),
    ([_info(), {"frame_id": "2", "platform": "Drone"}], "info[1]: lacks 'point_clout_path'"),
    ([_info(platform="Boat")], "unknown platform 'Boat'"),
    ([_info(point_clout_path="/etc/passwd")], "must be relative to the dataset root"),
    ([_info(point_clout_path="../../x.bin")], "must be relative to the dataset root"),
    ([_info(annos={"gt_names": np.array(["Car"]), "gt_boxes_lidar": np.ones((1, 6))})], "must be (M, 7)"),
    ([_info(annos={"gt_names": np.array(["Cyclist"]), "gt_boxes_lidar": np.ones((1, 7))})], "unknown class names ['Cyclist']"),
    ([_info(annos={"gt_names": np.array(["Car", "Car"]), "gt_boxes_lidar": np.ones((1, 7))})], "1 boxes but 2 names"),
    ([_info(annos={"gt_names": ["Car"], "gt_boxes_lidar": np.full((1, 7), np.nan)})], "NaN or infinite"),
    ([_info(annos={"gt_names": ["Car"]})], "annos lacks 'gt_boxes_lidar'"),
])
def test_bad_info_structure(tmp_path, payload, problem):
    path = tmp_path / "infos.pkl"
    path.write_bytes(pickle.dumps(payload))
    with raises(path, problem):
        pi3det.read_infos(path)


def test_truncated_pickle_and_writer_validation(tmp_path):
    path = tmp_path / "infos.pkl"
    path.write_bytes(pickle.dumps([_info()])[:-10])
    with raises(path, "pickle"):
        pi3det.read_infos(path)
    with raises(tmp_path / "w.pkl", "unknown platform"):
        pi3det.write_infos(tmp_path / "w.pkl", [_info(), _info(platform="Car")])
    assert not (tmp_path / "w.pkl").exists()
    # Pi3DET's own "Vehicle" name is accepted and stored as Car.
    path.write_bytes(pickle.dumps([_info(annos={"gt_names": np.array(["Vehicle"], dtype=object),
                                                "gt_boxes_lidar": np.ones((1, 7))})], protocol=2))
    assert pi3det.read_infos(path)[0]["annos"]["gt_names"].tolist() == ["Car"]


# ------------------------------------------------------- writers and atomicity


def test_writers_validate_shapes_and_dtypes(tmp_path):
    out = tmp_path / "x.bin"
    for bad, problem in [
        (np.zeros((5, 3), np.float32), "must have shape (N, 4)"),
        (np.zeros(8, np.float32), "must have shape (N, 4)"),
        (np.full((2, 4), "a"), "must be a real numeric array"),
        (np.zeros((2, 4), complex), "must be a real numeric array"),
    ]:
        with raises(out, problem):
            semantickitti.write_points(out, bad)
    with raises(out, "semantic ids values 0..70000 do not fit in uint16"):
        semantickitti.write_label(out, np.array([0, 70000]), np.zeros(2, np.uint16))
    with raises(out, "instance ids has 1 entries for 2 points"):
        semantickitti.write_label(out, np.array([0, 1]), np.zeros(1, np.uint16))
    with raises(out, "semantic ids must be an integer array"):
        semantickitti.write_label(out, np.array([0.5, 1.0]), None)
    assert not out.exists()
    # A scan with labels requested but none present writes neither file.
    with raises(tmp_path / "s.label", "no semantic labels"):
        semantickitti.write_scan(Scan(points(3)), tmp_path / "s.bin", tmp_path / "s.label")
    assert not (tmp_path / "s.bin").exists()
    assert list(tmp_path.iterdir()) == []


def test_failed_write_keeps_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    out = tmp_path / "scan.bin"
    semantickitti.write_points(out, points(3))
    before = out.read_bytes()
    with raises(out, "must have shape"):
        semantickitti.write_points(out, np.zeros((3, 5)))
    assert out.read_bytes() == before

    # Fail half-way through the byte stream: the old file must survive intact.
    class _HalfWriter:
        def __init__(self, data):
            self.data = data

        def tofile(self, target):
            with open(target, "wb") as fh:
                fh.write(self.data.tobytes()[:7])
            raise OSError("disk full")

    class _NumpyProxy:
        def __getattr__(self, name):
            return getattr(np, name)

        @staticmethod
        def ascontiguousarray(array, dtype=None):
            return _HalfWriter(np.ascontiguousarray(array, dtype=dtype))

    monkeypatch.setattr(pointfile, "np", _NumpyProxy())
    with pytest.raises(OSError, match="disk full"):
        semantickitti.write_points(out, points(50))
    with pytest.raises(OSError, match="disk full"):
        semantickitti.write_points(tmp_path / "new.bin", points(50))
    monkeypatch.undo()
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.bin"]  # no temporaries, no new.bin


def test_error_messages_are_one_line(tmp_path):
    path = tmp_path / "bad.bin"
    path.write_bytes(b"\0" * 17)
    with pytest.raises(InputError) as info:
        semantickitti.read_scan(path)
    assert re.fullmatch(r".*bad\.bin: size 17 bytes is not a multiple of 16 \(float32 x,y,z,remission\)",
                        str(info.value))
    assert info.value.path == str(path)
