"""omnilidar export: OpenPCDet custom-dataset and mmdet3d 1.x info files, read back field by field."""

from __future__ import annotations

import io
import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from omnilidar.cli import main
from omnilidar.downstream.det.pseudo_boxes import write_shard
from omnilidar.io import semantickitti
from omnilidar.io.atomic import atomic_path

# Two sample shards of three scans each; scan 000004 came out empty. Boxes are axis-aligned or
# turned, so that the points inside them are known by construction.
BOXES = {
    "000000": ([[10.0, 2.0, -1.0, 4.0, 2.0, 1.5, 0.3], [20.0, -5.0, -0.9, 0.8, 0.6, 1.8, -2.0]], ["Car", "Pedestrian"]),
    "000001": ([], []),
    "000002": ([[15.0, 0.5, -1.2, 4.5, 1.9, 1.6, 3.0]], ["Car"]),
    "000003": ([[8.0, -3.0, -1.0, 3.9, 1.7, 1.5, -0.7]], ["Car"]),
    "000004": ([], []),
    "000005": ([[30.0, 10.0, -1.1, 0.7, 0.7, 1.7, 1.2]], ["Pedestrian"]),
}
# mmdet3d's configs/_base_/datasets/semantickitti.py labels_map (raw SemanticKITTI id -> its class index, 19 ignored).
MMDET3D_LABELS_MAP = {0: 19, 1: 19, 10: 0, 11: 1, 13: 4, 15: 2, 16: 4, 18: 3, 20: 4, 30: 5, 31: 6, 32: 7, 40: 8, 44: 9,
                      48: 10, 49: 11, 50: 12, 51: 13, 52: 19, 60: 8, 70: 14, 71: 15, 72: 16, 80: 17, 81: 18, 99: 19,
                      252: 0, 253: 6, 254: 5, 255: 7, 256: 4, 257: 4, 258: 3, 259: 4}


class PlainUnpickler(pickle.Unpickler):
    """Loads builtins and numpy arrays only: what the exported pickles may hold."""

    def find_class(self, module, name):
        if module.split(".")[0] != "numpy":
            raise pickle.UnpicklingError(f"{module}.{name}")
        return super().find_class(module, name)


def load_pickle(path: Path):
    return PlainUnpickler(io.BytesIO(path.read_bytes())).load()


def scan_points(name: str) -> np.ndarray:
    """A scan: 60 points inside each box (at known offsets) plus 200 scattered far from every box."""
    if name == "000004":
        return np.zeros((0, 4), np.float32)
    rng = np.random.default_rng(int(name))
    parts = []
    for box in BOXES[name][0]:
        x, y, z, dx, dy, dz, h = box
        local = rng.uniform(-0.45, 0.45, (60, 3)) * [dx, dy, dz]
        c, s = np.cos(h), np.sin(h)
        parts.append(np.column_stack([x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1],
                                      z + local[:, 2], rng.uniform(0, 1, 60)]))
    parts.append(np.column_stack([rng.uniform(-60, -40, (200, 2)), rng.uniform(-2, 2, 200), rng.uniform(0, 1, 200)]))
    return np.concatenate(parts).astype(np.float32)


def scan_labels(name: str, n: int) -> np.ndarray:
    """Raw SemanticKITTI labels the way the pseudo-labeller writes them: train ids through LEARNING_MAP_INV."""
    train = np.random.default_rng(100 + int(name)).integers(0, semantickitti.NUM_CLASSES, n).astype(np.uint8)
    return semantickitti.to_raw_ids(train).astype(np.uint32)


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    root = tmp_path_factory.mktemp("export_inputs")
    samples, labels, boxes = [], [], []
    for k, names in enumerate((["000000", "000001", "000002"], ["000003", "000004", "000005"])):
        shard = root / "samples" / "Drone" / f"shard_{k}"
        with atomic_path(shard) as tmp:
            (tmp / "velodyne").mkdir(parents=True)
            for name in names:
                scan_points(name).tofile(tmp / "velodyne" / f"{name}.bin")
        pseudo = root / "pseudo" / "Drone" / f"shard_{k}"
        with atomic_path(pseudo) as tmp:
            (tmp / "labels").mkdir(parents=True)
            for name in names:
                semantickitti.write_label(tmp / "labels" / f"{name}.label", scan_labels(name, len(scan_points(name))))
        preds = {n: {"boxes": np.asarray(BOXES[n][0], np.float32).reshape(-1, 7), "scores": np.ones(len(BOXES[n][1])),
                     "names": BOXES[n][1]} for n in names}
        box_dir = root / "pseudo_boxes" / "Drone" / f"shard_{k}"
        write_shard(shard, "Drone", preds, 0.5, box_dir, {"detector": "voxel_rcnn"}, 0.0)
        samples.append(shard), labels.append(pseudo), boxes.append(box_dir)
    return samples, labels, boxes


def export(tmp_path, fmt, samples, *, labels=None, boxes=None, val_every=2, name="out"):
    out = tmp_path / name
    argv = ["export", "--format", fmt, "--samples", *map(str, samples), "--out", str(out), "--val-every", str(val_every)]
    if labels:
        argv += ["--labels", *map(str, labels)]
    if boxes:
        argv += ["--boxes", *map(str, boxes)]
    return main(argv), out


# Exported ids 000000..000004 are the non-empty scans in shard order; the first and every 2nd go to val.
EXPORTED = ["000000", "000001", "000002", "000003", "000005"]
SPLIT = {"val": ["000000", "000002", "000004"], "train": ["000001", "000003"]}


def source_of(export_id: str) -> str:
    return EXPORTED[int(export_id)]


def test_openpcdet_custom_dataset(tmp_path, shards, capsys):
    samples, _, boxes = shards
    code, out = export(tmp_path, "openpcdet", samples, boxes=boxes)
    assert code == 0
    printed = capsys.readouterr().out
    assert "Car 1, Pedestrian 0" in printed and "note: no train box of class Pedestrian" in printed
    for split, ids in SPLIT.items():
        assert (out / "ImageSets" / f"{split}.txt").read_text().split() == ids
        infos = load_pickle(out / f"custom_infos_{split}.pkl")
        assert [i["point_cloud"]["lidar_idx"] for i in infos] == ids  # ImageSets order = info order
        for info, export_id in zip(infos, ids):
            src_boxes, src_names = BOXES[source_of(export_id)]
            assert set(info) == {"point_cloud", "annos"} and info["point_cloud"] == {"num_features": 4, "lidar_idx": export_id}
            annos = info["annos"]
            assert set(annos) == {"name", "gt_boxes_lidar"}
            assert annos["name"].dtype.kind == "U" and annos["name"].tolist() == src_names
            assert annos["gt_boxes_lidar"].dtype == np.float32 and annos["gt_boxes_lidar"].shape == (len(src_names), 7)
            np.testing.assert_array_equal(annos["gt_boxes_lidar"], np.asarray(src_boxes, np.float32).reshape(-1, 7))
            points = np.load(out / "points" / f"{export_id}.npy")
            assert points.dtype == np.float32 and points.shape[1] == 4
            np.testing.assert_array_equal(points, scan_points(source_of(export_id)))
            # labels/<id>.txt as CustomDataset.get_label parses it: float32 boxes, last field the name
            lines = [line.strip().split(" ") for line in (out / "labels" / f"{export_id}.txt").read_text().splitlines()]
            assert [line[-1] for line in lines] == src_names
            np.testing.assert_array_equal(np.array([line[:-1] for line in lines], dtype=np.float32).reshape(-1, 7),
                                          annos["gt_boxes_lidar"])
    db = load_pickle(out / "custom_dbinfos_train.pkl")
    train_boxes = [(i, b, n) for e in SPLIT["train"] for i, (b, n) in enumerate(zip(*BOXES[source_of(e)]))]
    assert sorted(db) == ["Car", "Pedestrian"]  # every exported class, also one with no train box (Pedestrian)
    assert {k: len(v) for k, v in db.items()} == {c: sum(n == c for _, _, n in train_boxes) for c in db} == {"Car": 1, "Pedestrian": 0}
    for entries in db.values():
        for entry in entries:
            assert set(entry) == {"name", "path", "gt_idx", "box3d_lidar", "num_points_in_gt"}
            gt_points = np.fromfile(out / entry["path"], np.float32).reshape(-1, 4)
            assert entry["num_points_in_gt"] == len(gt_points) == 60  # the 60 points placed in it, none else
            assert entry["box3d_lidar"].dtype == np.float32
            assert np.abs(gt_points[:, :3]).max() < np.linalg.norm(entry["box3d_lidar"][3:6])  # relative to the centre
    record = json.loads((out / "export.json").read_text())
    assert record["empty_scans_left_out"] == [str(samples[1] / "velodyne" / "000004.bin")]
    assert [f["id"] for f in record["frames"]] == [f"{i:06d}" for i in range(5)]


def test_mmdet3d_semantickitti_infos_keep_raw_ids(tmp_path, shards):
    samples, labels, _ = shards
    code, out = export(tmp_path, "mmdet3d-seg", samples, labels=labels)
    assert code == 0
    lut = np.full(1 << 16, -1)
    for raw, cls in MMDET3D_LABELS_MAP.items():
        lut[raw] = cls
    for split, ids in SPLIT.items():
        infos = load_pickle(out / f"semantickitti_infos_{split}.pkl")
        assert infos["metainfo"] == {"DATASET": "SemanticKITTI"}
        assert [d["sample_id"] for d in infos["data_list"]] == ids
        seq = "08" if split == "val" else "00"
        for entry, export_id in zip(infos["data_list"], ids):
            assert entry["lidar_points"] == {"lidar_path": f"sequences/{seq}/velodyne/{export_id}.bin", "num_pts_feats": 4}
            assert entry["pts_semantic_mask_path"] == f"sequences/{seq}/labels/{export_id}.label"
            points = np.fromfile(out / entry["lidar_points"]["lidar_path"], np.float32).reshape(-1, 4)
            np.testing.assert_array_equal(points, scan_points(source_of(export_id)))
            # as mmdet3d loads it: int32, % 2**16, then its labels_map
            raw = np.fromfile(out / entry["pts_semantic_mask_path"], np.int32).astype(np.int64) % 2**16
            assert len(raw) == len(points)
            ours = semantickitti.to_train_ids(raw.astype(np.uint16)).astype(np.int64)
            expected = np.where(ours == 0, 19, ours - 1)  # our train id t is mmdet3d's t - 1, our ignore its 19
            np.testing.assert_array_equal(lut[raw], expected)
            assert (lut[raw] >= 0).all()


def lidar_from_mmdet3d(bbox_3d: list[float], lidar2cam) -> np.ndarray:
    """A camera box turned back into our LiDAR box the way mmdet3d does it
    (CameraInstance3DBoxes.convert_to(LIDAR, inv(lidar2cam)): points through the matrix,
    sizes (x, z, y), yaw -yaw - pi/2), then its bottom centre raised to the box centre."""
    cam = np.asarray(bbox_3d, np.float64)
    xyz = np.linalg.inv(np.asarray(lidar2cam)) @ np.append(cam[:3], 1.0)
    dx, dy, dz = cam[3], cam[5], cam[4]
    yaw = (-cam[6] - np.pi / 2 + np.pi) % (2 * np.pi) - np.pi
    return np.array([xyz[0], xyz[1], xyz[2] + dz / 2, dx, dy, dz, yaw])


def test_mmdet3d_kitti_infos_round_trip_to_lidar_boxes(tmp_path, shards):
    samples, _, boxes = shards
    code, out = export(tmp_path, "mmdet3d-det", samples, boxes=boxes)
    assert code == 0
    classes = ("Pedestrian", "Cyclist", "Car", "Van", "Truck", "Person_sitting", "Tram", "Misc")
    for split, ids in SPLIT.items():
        infos = load_pickle(out / f"kitti_infos_{split}.pkl")
        assert infos["metainfo"] == {"categories": {c: i for i, c in enumerate(classes)}, "dataset": "kitti",
                                     "info_version": "1.1"}
        for info, export_id in zip(infos["data_list"], ids):
            assert info["sample_idx"] == int(export_id) and isinstance(info["sample_idx"], int)
            assert info["lidar_points"]["lidar_path"] == f"{export_id}.bin" and info["lidar_points"]["num_pts_feats"] == 4
            points = np.fromfile(out / "training" / "velodyne" / f"{export_id}.bin", np.float32).reshape(-1, 4)
            np.testing.assert_array_equal(points, scan_points(source_of(export_id)))
            cam2 = info["images"]["CAM2"]
            np.testing.assert_array_equal(np.asarray(cam2["lidar2img"]), np.asarray(cam2["cam2img"]) @ np.asarray(cam2["lidar2cam"]))
            src_boxes, src_names = BOXES[source_of(export_id)]
            assert len(info["instances"]) == len(src_names)
            for inst, box, name in zip(info["instances"], src_boxes, src_names):
                assert inst["bbox_label_3d"] == inst["bbox_label"] == classes.index(name)
                assert isinstance(inst["bbox_3d"], list) and len(inst["bbox_3d"]) == 7
                back = lidar_from_mmdet3d(inst["bbox_3d"], cam2["lidar2cam"])
                np.testing.assert_allclose(back[:6], np.float32(box)[:6], atol=1e-5)
                assert abs((back[6] - box[6] + np.pi) % (2 * np.pi) - np.pi) < 1e-5
                # KITTI camera convention: y down, so the stored bottom centre lies dz/2 below the box centre
                assert inst["bbox_3d"][1] == pytest.approx(-(box[2] - box[5] / 2), abs=1e-5)
                assert inst["bbox"] == [0.0, 0.0, 50.0, 50.0] and inst["difficulty"] == 0
                assert inst["num_lidar_pts"] == 60


def one_line_error(capsys, code, out, *needles):
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("$ omnilidar")]
    assert code == 2 and len(lines) == 1, err
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert not out.exists() and not list(out.parent.glob(f".{out.name}.*"))


def copy_tree(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_bad_input_is_one_line_and_writes_nothing(tmp_path, shards, capsys):
    samples, labels, boxes = shards
    code, out = export(tmp_path, "openpcdet", samples)
    one_line_error(capsys, code, out, "--format openpcdet needs --boxes")
    code, out = export(tmp_path, "mmdet3d-seg", samples, labels=labels, boxes=boxes)
    one_line_error(capsys, code, out, "does not use --boxes")
    code, out = export(tmp_path, "mmdet3d-seg", samples, labels=labels[:1])
    one_line_error(capsys, code, out, "2 sample shards but 1 pseudo-label shards")

    # a scan changed after its shard was written
    tampered = copy_tree(samples[0], tmp_path / "tampered")
    data = bytearray((tampered / "velodyne" / "000002.bin").read_bytes())
    data[0] ^= 1
    (tampered / "velodyne" / "000002.bin").write_bytes(bytes(data))
    code, out = export(tmp_path, "mmdet3d-det", [tampered], boxes=boxes[:1])
    one_line_error(capsys, code, out, "000002.bin", "differs from its shard's MANIFEST.sha256")

    # no manifest: not a finished shard
    unfinished = copy_tree(samples[0], tmp_path / "unfinished")
    (unfinished / "MANIFEST.sha256").unlink()
    code, out = export(tmp_path, "openpcdet", [unfinished], boxes=boxes[:1])
    one_line_error(capsys, code, out, "unfinished", "has no MANIFEST.sha256")

    # boxes of another shard
    code, out = export(tmp_path, "openpcdet", samples, boxes=boxes[::-1])
    one_line_error(capsys, code, out, "infos.pkl", "does not match sample shard")

    # pseudo-labels whose count differs from the scan (manifest rewritten, so only the count is wrong)
    from omnilidar.manifest import write_manifest

    short = copy_tree(labels[0], tmp_path / "short_labels")
    semantickitti.write_label(short / "labels" / "000000.label", np.zeros(5, np.uint32))
    write_manifest(short)
    code, out = export(tmp_path, "mmdet3d-seg", [samples[0]], labels=[short])
    one_line_error(capsys, code, out, "000000.label", "holds 5 labels but scan")

    # labels that are not SemanticKITTI raw ids
    odd = copy_tree(labels[0], tmp_path / "odd_labels")
    np.full(len(scan_points("000000")), 7, np.uint32).tofile(odd / "labels" / "000000.label")
    write_manifest(odd)
    code, out = export(tmp_path, "mmdet3d-seg", [samples[0]], labels=[odd])
    one_line_error(capsys, code, out, "000000.label", "[7] are not SemanticKITTI raw ids")

    # an --out that is not an earlier export is never replaced
    keep = tmp_path / "precious"
    keep.mkdir()
    (keep / "data.txt").write_text("keep me")
    assert main(["export", "--format", "openpcdet", "--samples", str(samples[0]), "--boxes", str(boxes[0]),
                 "--out", str(keep)]) == 2
    assert "is not an earlier export" in capsys.readouterr().err and (keep / "data.txt").read_text() == "keep me"


def test_a_second_export_replaces_the_first(tmp_path, shards):
    samples, _, boxes = shards
    assert export(tmp_path, "openpcdet", samples, boxes=boxes, val_every=0)[0] == 0
    code, out = export(tmp_path, "openpcdet", samples[:1], boxes=boxes[:1], val_every=0)
    assert code == 0
    assert (out / "ImageSets" / "train.txt").read_text().split() == ["000000", "000001", "000002"]
    assert (out / "ImageSets" / "val.txt").read_text() == "" and load_pickle(out / "custom_infos_val.pkl") == []
    assert not (out / "points" / "000003.npy").exists()


def test_mmdet3d_object_sample_database(tmp_path, shards):
    samples, _, boxes = shards
    code, out = export(tmp_path, "mmdet3d-det", samples, boxes=boxes, val_every=0)
    assert code == 0
    db = load_pickle(out / "kitti_dbinfos_train.pkl")
    assert sorted(db) == ["Car", "Pedestrian"] and [len(db["Car"]), len(db["Pedestrian"])] == [3, 2]
    groups = []
    for name, entries in db.items():
        for e in entries:
            assert set(e) == {"name", "path", "image_idx", "gt_idx", "box3d_lidar", "num_points_in_gt", "difficulty",
                              "group_id", "score"}
            src_box = np.float32(BOXES[source_of(f"{e['image_idx']:06d}")][0][e["gt_idx"]])
            assert e["box3d_lidar"].dtype == np.float32
            np.testing.assert_allclose(e["box3d_lidar"], [*src_box[:2], src_box[2] - src_box[5] / 2, *src_box[3:]], atol=1e-6)
            pts = np.fromfile(out / e["path"], np.float32).reshape(-1, 4)
            assert e["num_points_in_gt"] == len(pts) == 60
            assert (pts[:, 2] >= -1e-4).all() and (pts[:, 2] <= src_box[5] + 1e-4).all()  # above the bottom centre
            groups.append(e["group_id"])
    assert sorted(groups) == list(range(5))


def test_a_shard_written_by_the_sampler_exports(tmp_path):
    """The real `omnilidar sample` shard layout (tiny generator), labelled the way the pseudo-labeller writes."""
    import torch

    from omnilidar.generator.checkpoint import CHECKPOINT_FORMAT, load_generator
    from omnilidar.generator.sampling import sample_shard
    from omnilidar.generator.text import build_prompt_cache
    from omnilidar.generator.unet import build_denoiser
    from test_generator_fixtures import tiny_settings
    from test_generator_training import FakeEncoder

    settings = tiny_settings()
    cache = build_prompt_cache(settings["prompts"], FakeEncoder())
    with torch.random.fork_rng():
        torch.manual_seed(0)
        den = build_denoiser(settings, cache["dim"], 1)
        for p in den.parameters():
            p.data.add_(0.05 * torch.randn_like(p))
    payload = {"format": CHECKPOINT_FORMAT, "state_dict": den.state_dict(), "config": settings, "domains": ["Vehicle"],
               "text": {"encoder": "fake", "model": "fake", "dim": cache["dim"]}, "seed": 0, "iterations": 0}
    torch.save(payload, tmp_path / "ckpt.pt")
    den, payload = load_generator(tmp_path / "ckpt.pt")
    shard = tmp_path / "samples" / "vehicle" / "shard_0"
    sample_shard(den, payload, cache, "Vehicle", 0, 2, settings["sampling"], 3, shard, log=lambda *_: None)
    scans = sorted((shard / "velodyne").glob("*.bin"))
    pseudo = tmp_path / "pseudo" / "vehicle" / "shard_0"
    with atomic_path(pseudo) as tmp:
        (tmp / "labels").mkdir(parents=True)
        for s in scans:
            semantickitti.write_label(tmp / "labels" / f"{s.stem}.label", scan_labels("1", s.stat().st_size // 16))
    code, out = export(tmp_path, "mmdet3d-seg", [shard], labels=[pseudo], val_every=0)
    assert code == 0
    infos = load_pickle(out / "semantickitti_infos_train.pkl")["data_list"]
    kept = [s for s in scans if s.stat().st_size]
    assert len(infos) == len(kept) > 0
    for entry, scan in zip(infos, kept):
        assert (out / entry["lidar_points"]["lidar_path"]).read_bytes() == scan.read_bytes()


def test_shift_coor_moves_points_and_boxes_alike(tmp_path, shards):
    samples, _, boxes = shards
    out = tmp_path / "shifted"
    assert main(["export", "--format", "openpcdet", "--samples", str(samples[0]), "--boxes", str(boxes[0]),
                 "--shift-coor", "0", "0", "8.27", "--out", str(out)]) == 0
    info = load_pickle(out / "custom_infos_train.pkl")[0]
    shifted = np.asarray(BOXES["000000"][0], np.float32)
    shifted[:, 2] += np.float32(8.27)
    np.testing.assert_array_equal(info["annos"]["gt_boxes_lidar"], shifted)
    points = np.load(out / "points" / "000000.npy")
    np.testing.assert_array_equal(points[:, 2], scan_points("000000")[:, 2] + np.float32(8.27))
    np.testing.assert_array_equal(points[:, [0, 1, 3]], scan_points("000000")[:, [0, 1, 3]])
    assert json.loads((out / "export.json").read_text())["shift_coor"] == [0.0, 0.0, 8.27]
    db = load_pickle(out / "custom_dbinfos_train.pkl")
    assert [e["num_points_in_gt"] for e in db["Car"]] == [60, 60]  # the shifted points still fall in the shifted box


def test_rename_class_for_openpcdet_custom_configs(tmp_path, shards, capsys):
    samples, _, boxes = shards
    out = tmp_path / "renamed"
    assert main(["export", "--format", "openpcdet", "--samples", str(samples[0]), "--boxes", str(boxes[0]),
                 "--rename-class", "Car=Vehicle", "--out", str(out)]) == 0
    info = load_pickle(out / "custom_infos_train.pkl")[0]
    assert info["annos"]["name"].tolist() == ["Vehicle", "Pedestrian"]
    assert (out / "labels" / "000000.txt").read_text().splitlines()[0].endswith(" Vehicle")
    assert sorted(load_pickle(out / "custom_dbinfos_train.pkl")) == ["Pedestrian", "Vehicle"]
    code = main(["export", "--format", "mmdet3d-det", "--samples", str(samples[0]), "--boxes", str(boxes[0]),
                 "--rename-class", "Car=Vehicle", "--out", str(tmp_path / "kitti")])
    one_line_error(capsys, code, tmp_path / "kitti", "['Vehicle'] have no KITTI class")
    code = main(["export", "--format", "openpcdet", "--samples", str(samples[0]), "--boxes", str(boxes[0]),
                 "--rename-class", "Truck=Lorry", "--out", str(tmp_path / "bad")])
    one_line_error(capsys, code, tmp_path / "bad", "--rename-class 'Truck=Lorry'")
