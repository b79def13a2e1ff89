"""omnilidar convert-nuscenes on a v1.0-mini-like release: devkit tables, a real sweep."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from real_samples import REAL

from omnilidar.cli import main
from omnilidar.data.index import build_index
from omnilidar.io import nuscenes

ROOT = Path(__file__).resolve().parents[1]
REAL_SWEEP = "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
# The devkit's official v1.0-mini scene lists (nuscenes/utils/splits.py).
SPLITS_PY = """
mini_train = \\
    ['scene-0061', 'scene-0553', 'scene-0655', 'scene-0757', 'scene-0796', 'scene-1077', 'scene-1094',
     'scene-1100']

mini_val = \\
    ['scene-0103', 'scene-0916']
"""


def real_data_root() -> Path:
    """Where the real samples are (tests/real_samples.py: OMNILIDAR_REAL_DATA)."""
    return REAL


def _token(kind: str, i: int) -> str:
    return f"{kind}{i:028x}"[:32]


def make_release(tmp: Path, real_sweep: Path) -> Path:
    """A dataroot with v1.0-mini tables: scene-0061 (mini_train: the real sweep with lidarseg,
    a lidar sweep that is not a key frame, a camera image), scene-0103 (mini_val: a synthetic
    sweep without lidarseg) and scene-9999 (in neither list, like a test scene)."""
    root, tables = tmp / "nuscenes", tmp / "nuscenes" / "v1.0-mini"
    (root / "samples" / "LIDAR_TOP").mkdir(parents=True)
    (root / "sweeps" / "LIDAR_TOP").mkdir(parents=True)
    (root / "lidarseg" / "v1.0-mini").mkdir(parents=True)
    tables.mkdir()
    rng = np.random.default_rng(0)
    synthetic = rng.uniform(-20, 20, (300, 5)).astype(np.float32)
    synthetic[:, 4] = rng.integers(0, 32, 300)
    sweeps = {"real": (root / "samples/LIDAR_TOP" / REAL_SWEEP, real_sweep.read_bytes()),
              "val": (root / "samples/LIDAR_TOP/n008-2018-08-01-15-16-36-0400__LIDAR_TOP__1533151603547590.pcd.bin",
                      synthetic.tobytes()),
              "test": (root / "samples/LIDAR_TOP/n015-2018-10-08-15-36-50+0800__LIDAR_TOP__1538984233547259.pcd.bin",
                       synthetic.tobytes()),
              "sweep": (root / "sweeps/LIDAR_TOP/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927697951.pcd.bin",
                        synthetic.tobytes())}
    for path, data in sweeps.values():
        path.write_bytes(data)
    n_real = len(sweeps["real"][1]) // 20
    seg = rng.integers(0, 32, n_real).astype(np.uint8)
    sensor = [{"token": _token("s", 0), "channel": "LIDAR_TOP", "modality": "lidar"},
              {"token": _token("s", 1), "channel": "CAM_FRONT", "modality": "camera"}]
    calibrated = [{"token": _token("c", 0), "sensor_token": _token("s", 0), "translation": [0.9, 0, 1.8]},
                  {"token": _token("c", 1), "sensor_token": _token("s", 1), "translation": [1.7, 0, 1.5]}]
    scene = [{"token": _token("e", i), "name": name, "nbr_samples": 1, "first_sample_token": _token("a", i),
              "last_sample_token": _token("a", i), "log_token": _token("l", i), "description": ""}
             for i, name in enumerate(("scene-0061", "scene-0103", "scene-9999"))]
    sample = [{"token": _token("a", i), "timestamp": 1532402927647951 + i, "prev": "", "next": "",
               "scene_token": _token("e", i)} for i in range(3)]

    def sd(i, sample_i, path, key, calib=0, fileformat="pcd"):
        return {"token": _token("d", i), "sample_token": _token("a", sample_i), "ego_pose_token": _token("p", i),
                "calibrated_sensor_token": _token("c", calib), "timestamp": 1532402927647951 + i,
                "fileformat": fileformat, "is_key_frame": key, "height": 0, "width": 0,
                "filename": str(path.relative_to(root)), "prev": "", "next": ""}

    sample_data = [sd(0, 0, sweeps["real"][0], True), sd(1, 1, sweeps["val"][0], True),
                   sd(2, 2, sweeps["test"][0], True), sd(3, 0, sweeps["sweep"][0], False),
                   sd(4, 0, root / "samples/CAM_FRONT/x.jpg", True, calib=1, fileformat="jpg")]
    lidarseg = [{"token": _token("d", 0), "sample_data_token": _token("d", 0),
                 "filename": f"lidarseg/v1.0-mini/{_token('d', 0)}_lidarseg.bin"}]
    seg.tofile(root / lidarseg[0]["filename"])
    for name, rows in (("sensor", sensor), ("calibrated_sensor", calibrated), ("scene", scene),
                       ("sample", sample), ("sample_data", sample_data), ("lidarseg", lidarseg)):
        (tables / f"{name}.json").write_text(json.dumps(rows, indent=1))
    (tmp / "splits.py").write_text(SPLITS_PY)
    return tables


@pytest.fixture
def release(tmp_path) -> Path:
    sweep = real_data_root() / "nuscenes" / REAL_SWEEP
    if not sweep.is_file():
        pytest.skip(f"real nuScenes sweep not found at {sweep} (set OMNILIDAR_REAL_DATA)")
    return make_release(tmp_path, sweep)


def test_mini_release_converts_to_our_layout_and_indexes(release, tmp_path, capsys):
    out = tmp_path / "converted"
    assert main(["convert-nuscenes", "--tables", str(release), "--out", str(out),
                 "--splits-file", str(tmp_path / "splits.py")]) == 0
    assert "train: 1 key frames, 1 with lidarseg" in capsys.readouterr().out
    name = REAL_SWEEP[: -len(".pcd.bin")]
    scan_path = out / "train" / "samples" / "LIDAR_TOP" / REAL_SWEEP
    assert scan_path.is_symlink() and scan_path.read_bytes() == (release.parent / "samples/LIDAR_TOP" / REAL_SWEEP).read_bytes()
    index = build_index("nuscenes", out)
    assert [len(index["splits"][s]) for s in ("train", "val")] == [1, 1]  # test scene and non-key sweep skipped
    scan = nuscenes.read_scan(scan_path)
    labels = nuscenes.read_lidarseg(out / "train" / "lidarseg" / f"{name}_lidarseg.bin", len(scan.points))
    assert len(labels) == len(scan.points) > 1000
    assert not (out / "val" / "lidarseg").exists()  # the val sweep has no lidarseg entry


def test_bad_release_is_one_clear_error_and_writes_nothing(release, tmp_path, capsys):
    seg = next((release.parent / "lidarseg" / "v1.0-mini").glob("*.bin"))
    seg.write_bytes(seg.read_bytes()[:-3])
    out = tmp_path / "converted"
    assert main(["convert-nuscenes", "--tables", str(release), "--out", str(out),
                 "--splits-file", str(tmp_path / "splits.py")]) == 2
    err = capsys.readouterr().err
    assert f"{seg.name}: has " in err and "labels but its sweep" in err and not out.exists()
    (tmp_path / "splits.py").write_text("train = ['scene-0001']\n")
    assert main(["convert-nuscenes", "--tables", str(release), "--out", str(out),
                 "--splits-file", str(tmp_path / "splits.py")]) == 2
    assert "no list 'mini_train' for v1.0-mini" in capsys.readouterr().err
