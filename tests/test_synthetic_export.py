"""``omnilidar synthesize``: every layout is written atomically and reads back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from omnilidar.cli import main
from omnilidar.data.synthetic.export import NUSCENES_GENERAL, to_nuscenes_general
from omnilidar.data.synthetic.shards import planned_split_counts, shard_names
from omnilidar.config import section_defaults
from omnilidar.io import kitti360, nuscenes, pi3det, semantickitti
from omnilidar.io.semantickitti import LEARNING_MAP

TINY = {
    "world": {"margin_m": 40.0, "grid_m": 0.4},
    "datasets": {
        "semantickitti": {"sequences": ["00", "11"], "scans_per_sequence": 2, "scans_per_test_sequence": 1},
        "kitti360": {"sequences": [3], "scans_per_sequence": 2},
        "pi3det": {"platforms": {
            "vehicle": {"scenes": 1, "scans_per_scene": 1},
            "drone": {"scenes": 2, "scans_per_scene": 1, "val_fraction": 0.5},
            "quadruped": {"scenes": 1, "scans_per_scene": 1}}},
        "nuscenes": {"splits": {"train": {"scenes": 1, "scans_per_scene": 2}, "val": {"scenes": 1, "scans_per_scene": 1}}},
    },
}


def synth(dataset, shard, out, settings=TINY, seed=0):
    return main(["synthesize", dataset, "--shard", shard, "--settings", json.dumps(settings), "--seed", str(seed),
                 "--out", str(out)])


def test_semantickitti_layout_reads_back_and_test_sequences_have_no_labels(tmp_path, capsys):
    root = tmp_path / "semantickitti"
    assert synth("semantickitti", "00", root / "sequences" / "00") == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["scans"] == 2
    pairs = semantickitti.sequence_paths(root, "00")
    assert len(pairs) == 2
    for bin_path, label_path in pairs:
        scan = semantickitti.read_scan(bin_path, label_path)
        assert len(scan) > 20_000
        assert set(np.unique(scan.semantic).tolist()) <= set(LEARNING_MAP)
    assert synth("semantickitti", "11", root / "sequences" / "11") == 0
    assert not (root / "sequences" / "11" / "labels").exists()
    assert len(list((root / "sequences" / "11" / "velodyne").glob("*.bin"))) == 1
    # No temporary leftovers beside the shards.
    assert sorted(p.name for p in (root / "sequences").iterdir()) == ["00", "11"]


def test_same_seed_same_bytes_and_shards_independent(tmp_path):
    a, b, c = tmp_path / "a" / "00", tmp_path / "b" / "00", tmp_path / "c" / "00"
    assert synth("semantickitti", "00", a) == 0
    assert synth("semantickitti", "00", b) == 0
    assert synth("semantickitti", "00", c, seed=1) == 0
    fa = (a / "velodyne" / "000001.bin").read_bytes()
    assert fa == (b / "velodyne" / "000001.bin").read_bytes()
    assert (a / "labels" / "000001.label").read_bytes() == (b / "labels" / "000001.label").read_bytes()
    assert fa != (c / "velodyne" / "000001.bin").read_bytes()
    # A shard does not depend on which other shards are configured.
    other = json.loads(json.dumps(TINY))
    other["datasets"]["semantickitti"]["sequences"] = ["00", "05", "07"]
    d = tmp_path / "d" / "00"
    assert synth("semantickitti", "00", d, settings=other) == 0
    assert fa == (d / "velodyne" / "000001.bin").read_bytes()


def test_kitti360_layout(tmp_path):
    root = tmp_path / "kitti360"
    out = root / "data_3d_raw" / "2013_05_28_drive_0003_sync"
    assert synth("kitti360", "0003", out) == 0
    paths = kitti360.sequence_paths(root, 3)
    assert [p.name for p in paths] == ["0000000000.bin", "0000000001.bin"]
    assert paths[1] == kitti360.scan_path(root, 3, 1)
    assert len(kitti360.read_scan(paths[0])) > 20_000


@pytest.mark.parametrize("platform", ["vehicle", "drone", "quadruped"])
def test_pi3det_layout(tmp_path, platform):
    root = tmp_path / "pi3det"
    assert synth("pi3det", platform, root / platform) == 0
    infos = pi3det.read_infos(root / platform / f"{platform}_infos_train.pkl")
    val = pi3det.read_infos(root / platform / f"{platform}_infos_val.pkl")
    assert len(infos) + len(val) == (2 if platform == "drone" else 1)
    if platform == "drone":
        assert len(infos) == 1 and len(val) == 1
    for info in infos + val:
        assert info["platform"] == platform.capitalize()
        scan = pi3det.read_scan(info, root)
        assert len(scan) > 5_000
        names = set(info["annos"]["gt_names"].tolist())
        assert names <= ({"Car"} if platform == "drone" else {"Car", "Pedestrian"})
        sem, inst = semantickitti.read_label(root / platform / "labels" / f"{info['frame_id']}.label", len(scan))
        assert len(sem) == len(scan)


def test_nuscenes_layout(tmp_path):
    root = tmp_path / "nuscenes"
    assert synth("nuscenes", "train", root / "train") == 0
    sweeps = sorted((root / "train" / "samples" / "LIDAR_TOP").glob("*.pcd.bin"))
    assert len(sweeps) == 2
    for sweep in sweeps:
        scan = nuscenes.read_scan(sweep)
        values = scan.intensity
        assert values.max() > 1.0 and (values == np.round(values)).all() and values.max() <= 255
        assert scan.ring.min() >= 0 and scan.ring.max() <= 31
        seg = root / "train" / "lidarseg" / sweep.name.replace(".pcd.bin", "_lidarseg.bin")
        labels = nuscenes.read_lidarseg(seg, len(scan))
        assert set(np.unique(labels).tolist()) <= set(NUSCENES_GENERAL.values()) - {0}


def test_nuscenes_map_covers_every_synthetic_class():
    from omnilidar.data.synthetic import classes as C

    ids = np.array([C.CAR, C.PERSON, C.ROAD, C.SIDEWALK, C.VEGETATION, C.BUILDING, 999], np.uint16)
    assert to_nuscenes_general(ids).tolist() == [17, 2, 24, 26, 30, 28, 0]
    assert set(C.REFLECTIVITY) <= set(NUSCENES_GENERAL)


def test_bad_input_is_one_clear_error(tmp_path, capsys):
    assert synth("semantickitti", "15", tmp_path / "x") == 2
    assert "not configured" in capsys.readouterr().err
    assert synth("semantickitti", "00", tmp_path / "x", settings={"world": {"grid_m": -1}}) == 2
    assert "grid_m" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_default_shards_match_the_workflow_naming():
    d = section_defaults("synthetic")
    assert shard_names("semantickitti", d)[:2] == ["00", "01"]
    assert shard_names("kitti360", d)[0] == "0000"
    assert shard_names("pi3det", d) == ["vehicle", "drone", "quadruped"]
    assert shard_names("nuscenes", d) == ["train", "val"]


def test_planned_split_counts_are_what_the_written_world_indexes(tmp_path):
    """The workflow plans segment chains from planned_split_counts before the world exists: every
    dataset's planned {split: scans} equals its index once every shard is written."""
    from omnilidar.config import validate
    from omnilidar.data.index import build_index

    settings = validate(json.loads(json.dumps(TINY)), "synthetic.schema.yaml")
    where = {"semantickitti": lambda root, shard: root / "sequences" / shard,
             "kitti360": lambda root, shard: root / "data_3d_raw" / f"2013_05_28_drive_{shard}_sync",
             "pi3det": lambda root, shard: root / shard, "nuscenes": lambda root, shard: root / shard}
    for dataset, folder in where.items():
        root = tmp_path / dataset
        for shard in shard_names(dataset, settings):
            assert synth(dataset, shard, folder(root, shard)) == 0
        indexed = {split: len(entries) for split, entries in build_index(dataset, root)["splits"].items()}
        planned = planned_split_counts(dataset, settings)
        assert {k: v for k, v in planned.items() if v} == {k: v for k, v in indexed.items() if v}, dataset
    assert planned_split_counts("pi3det", settings)["drone_val"] == 1


def test_a_shard_is_written_from_its_own_settings_alone(tmp_path):
    """The workflow hands each shard only the shared keys and its own dataset entry (shard_settings,
    its provenance): the shard is the same bytes, and another dataset's, platform's or sequence's
    settings do not enter it, while its own do."""
    from omnilidar.data.synthetic.shards import shard_settings

    own = shard_settings(TINY, "pi3det", "quadruped")
    assert set(own["datasets"]) == {"pi3det"} and set(own["datasets"]["pi3det"]["platforms"]) == {"quadruped"}
    full, narrowed = tmp_path / "full" / "quadruped", tmp_path / "narrowed" / "quadruped"
    assert synth("pi3det", "quadruped", full) == 0 and synth("pi3det", "quadruped", narrowed, settings=own) == 0
    assert (full / "velodyne" / "000000.bin").read_bytes() == (narrowed / "velodyne" / "000000.bin").read_bytes()
    assert (full / "quadruped_infos_train.pkl").read_bytes() == (narrowed / "quadruped_infos_train.pkl").read_bytes()

    other = json.loads(json.dumps(TINY))
    other["datasets"]["pi3det"]["platforms"]["drone"]["scenes"] = 5
    other["datasets"]["semantickitti"]["sequences"] = ["00", "05", "11"]
    other["datasets"]["nuscenes"]["splits"]["val"]["scenes"] = 3
    assert shard_settings(other, "pi3det", "quadruped") == own
    assert shard_settings(other, "semantickitti", "00") == shard_settings(TINY, "semantickitti", "00")
    assert shard_settings(other, "semantickitti", "00")["datasets"]["semantickitti"]["sequences"] == ["00"]
    assert shard_settings(other, "nuscenes", "train") == shard_settings(TINY, "nuscenes", "train")
    other["datasets"]["pi3det"]["platforms"]["quadruped"]["pedestrians_per_100m"] = 40.0
    other["world"] = {**other["world"], "grid_m": 0.5}
    assert shard_settings(other, "pi3det", "quadruped") != own
    assert shard_settings(other, "pi3det", "drone") != shard_settings(TINY, "pi3det", "drone")  # the shared world


def test_a_platform_s_own_crowd_density_replaces_the_world_s_in_its_scenes_only(tmp_path):
    """pedestrians_per_100m of a Pi3DET platform: its scenes hold that crowd, whatever the world's."""
    empty = json.loads(json.dumps(TINY))
    empty["world"]["pedestrians_per_100m"] = 0.0
    empty["datasets"]["pi3det"]["platforms"]["quadruped"].update(pedestrians_per_100m=None, scans_per_scene=2)
    crowded = json.loads(json.dumps(empty))
    crowded["datasets"]["pi3det"]["platforms"]["quadruped"]["pedestrians_per_100m"] = 60.0

    def pedestrians(settings, name):
        assert synth("pi3det", "quadruped", tmp_path / name / "quadruped", settings=settings) == 0
        infos = pi3det.read_infos(tmp_path / name / "quadruped" / "quadruped_infos_train.pkl")
        return sum(int((np.asarray(i["annos"]["gt_names"]) == "Pedestrian").sum()) for i in infos)

    assert pedestrians(empty, "empty") == 0
    assert pedestrians(crowded, "crowded") >= 4
