"""Do OpenPCDet's and mmdet3d's own dataset classes read what ``omnilidar export`` writes?

Neither toolkit installs on a CPU-only machine (compiled CUDA ops), but their dataset code is
plain Python. Given a source checkout of either (nothing is installed or downloaded), this
imports that code straight from the checkout, with the few compiled or optional modules it
imports replaced by small stand-ins (points-in-boxes and BEV IoU by ours; image and shared-memory
modules, never called here, by empty modules), then:

- OpenPCDet: builds ``CustomDataset`` on the openpcdet export from the stock
  ``custom_dataset.yaml`` (classes cut to Vehicle / Pedestrian, voxelization left out, it needs
  spconv), draws every train frame (with gt_sampling from our database) and every val frame, and
  checks that ``get_infos`` (what ``create_custom_infos`` writes) on our ``points/`` and ``labels/``
  equals our ``custom_infos_*.pkl``;
- mmdet3d: builds ``KittiDataset`` on the mmdet3d-det export and checks that the
  ``gt_bboxes_3d`` it makes (LiDARInstance3DBoxes, back from our camera-frame boxes) are our boxes,
  and ``SemanticKittiDataset`` on the mmdet3d-seg export with the SemanticKITTI config's
  ``labels_map``: its class of every point is our train id minus one (ignore -> 19).

Prints one line per check; exits 1 when one fails.

    python benchmarks/check_export_toolkits.py --openpcdet ~/src/OpenPCDet --mmdet3d ~/src/mmdetection3d
"""

from __future__ import annotations

import argparse
import pickle
import sys
import tempfile
import types
from pathlib import Path

import numpy as np
import torch
import yaml

from omnilidar.cli import main as omnilidar
from omnilidar.geometry.rotated_iou import boxes_iou_bev
from omnilidar.geometry.points_in_boxes import points_in_boxes_mask
from omnilidar.downstream.det.pseudo_boxes import write_shard
from omnilidar.io import semantickitti
from omnilidar.io.atomic import atomic_path

# Per scan: (boxes x, y, z_centre, dx, dy, dz, heading; names). Scan 2 has no box.
SCANS = [
    ([[10.0, 2.0, -1.0, 4.0, 2.0, 1.5, 0.3], [20.0, -5.0, -0.9, 0.8, 0.6, 1.8, -2.0]], ["Car", "Pedestrian"]),
    ([[15.0, 0.5, -1.2, 4.5, 1.9, 1.6, 3.0], [12.0, 6.0, -0.9, 0.7, 0.7, 1.7, 1.2]], ["Car", "Pedestrian"]),
    ([], []),
    ([[8.0, -3.0, -1.0, 3.9, 1.7, 1.5, -0.7], [25.0, 3.0, -0.9, 0.8, 0.6, 1.8, 0.4]], ["Car", "Pedestrian"]),
    ([[30.0, 10.0, -1.1, 4.2, 1.8, 1.6, 1.2]], ["Car"]),
]
# configs/_base_/datasets/semantickitti.py of mmdet3d: raw SemanticKITTI id -> its class (19 ignored)
MMDET3D_LABELS_MAP = {0: 19, 1: 19, 10: 0, 11: 1, 13: 4, 15: 2, 16: 4, 18: 3, 20: 4, 30: 5, 31: 6, 32: 7, 40: 8, 44: 9,
                      48: 10, 49: 11, 50: 12, 51: 13, 52: 19, 60: 8, 70: 14, 71: 15, 72: 16, 80: 17, 81: 18, 99: 19,
                      252: 0, 253: 6, 254: 5, 255: 7, 256: 4, 257: 4, 258: 3, 259: 4}


def scan_points(k: int) -> np.ndarray:
    rng = np.random.default_rng(k)
    parts = []
    for x, y, z, dx, dy, dz, h in SCANS[k][0]:
        local = rng.uniform(-0.45, 0.45, (60, 3)) * [dx, dy, dz]
        c, s = np.cos(h), np.sin(h)
        parts.append(np.column_stack([x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1],
                                      z + local[:, 2], rng.uniform(0, 1, 60)]))
    parts.append(np.column_stack([rng.uniform(-60, -40, (300, 2)), rng.uniform(-2, 2, 300), rng.uniform(0, 1, 300)]))
    return np.concatenate(parts).astype(np.float32)


def make_exports(root: Path) -> dict[str, Path]:
    samples, labels, boxes = root / "samples", root / "labels", root / "boxes"
    with atomic_path(samples) as tmp:
        (tmp / "velodyne").mkdir(parents=True)
        for k in range(len(SCANS)):
            scan_points(k).tofile(tmp / "velodyne" / f"{k:06d}.bin")
    with atomic_path(labels) as tmp:
        (tmp / "labels").mkdir(parents=True)
        for k in range(len(SCANS)):
            train = np.random.default_rng(50 + k).integers(0, semantickitti.NUM_CLASSES, len(scan_points(k)))
            semantickitti.write_label(tmp / "labels" / f"{k:06d}.label", semantickitti.to_raw_ids(train.astype(np.uint8)))
    preds = {f"{k:06d}": {"boxes": np.asarray(b, np.float32).reshape(-1, 7), "scores": np.ones(len(n)), "names": n}
             for k, (b, n) in enumerate(SCANS)}
    write_shard(samples, "Quadruped", preds, 0.5, boxes, {"detector": "check"}, 0.0)
    out = {}
    for fmt, extra in (("openpcdet", ["--boxes", str(boxes), "--rename-class", "Car=Vehicle"]),
                       ("mmdet3d-det", ["--boxes", str(boxes)]), ("mmdet3d-seg", ["--labels", str(labels)])):
        out[fmt] = root / fmt
        if omnilidar(["export", "--format", fmt, "--samples", str(samples), *extra, "--val-every", "3",
                      "--out", str(out[fmt])]) != 0:
            raise SystemExit(f"omnilidar export --format {fmt} failed")
    return out


def stub(name: str, **attrs) -> types.ModuleType:
    module = types.ModuleType(name)
    module.__dict__.update(attrs)
    sys.modules[name] = module
    return module


def package(name: str, path: Path) -> types.ModuleType:
    """A package whose __init__ is not run (the toolkits' inits import every dataset and op)."""
    module = stub(name)
    module.__path__ = [str(path)]
    return module


def never_called(*_, **__):
    raise RuntimeError("compiled op stand-in called")


class AttrDict(dict):
    """easydict.EasyDict's behaviour as OpenPCDet uses it: nested dicts with attribute access."""

    def __init__(self, data=None):
        super().__init__()
        for key, value in (data or {}).items():
            self[key] = value

    def __setitem__(self, key, value):
        if isinstance(value, dict) and not isinstance(value, AttrDict):
            value = AttrDict(value)
        elif isinstance(value, list):
            value = [AttrDict(v) if isinstance(v, dict) and not isinstance(v, AttrDict) else v for v in value]
        super().__setitem__(key, value)

    def __getattr__(self, key):
        try:
            return self[key]
        except KeyError:
            raise AttributeError(key) from None

    __setattr__ = __setitem__


def check_openpcdet(src: Path, root: Path) -> list[str]:
    stub("easydict", EasyDict=AttrDict)
    for name in ("SharedArray", "torchvision", "cumm", "cumm.tensorview", "skimage.io", "skimage.transform"):
        stub(name)
    stub("skimage", io=sys.modules["skimage.io"], transform=sys.modules["skimage.transform"])
    for name, rel in (("pcdet", "pcdet"), ("pcdet.datasets", "pcdet/datasets"), ("pcdet.ops", "pcdet/ops"),
                      ("pcdet.ops.iou3d_nms", "pcdet/ops/iou3d_nms"), ("pcdet.ops.roiaware_pool3d", "pcdet/ops/roiaware_pool3d"),
                      ("pcdet.datasets.kitti", "pcdet/datasets/kitti"),
                      ("pcdet.datasets.kitti.kitti_object_eval_python", "pcdet/datasets/kitti/kitti_object_eval_python")):
        package(name, src / rel)
    stub("pcdet.datasets.kitti.kitti_object_eval_python.kitti_common")
    stub("pcdet.ops.roiaware_pool3d.roiaware_pool3d_utils",  # (M boxes, N points) int, as the CPU op
         points_in_boxes_cpu=lambda pts, boxes: points_in_boxes_mask(pts.float(), boxes.float()).T.int())
    stub("pcdet.ops.iou3d_nms.iou3d_nms_utils", boxes_bev_iou_cpu=lambda a, b: boxes_iou_bev(
        torch.as_tensor(a).float(), torch.as_tensor(b).float()).numpy())
    sys.path.insert(0, str(src))
    from pcdet.datasets.custom.custom_dataset import CustomDataset
    from pcdet.utils import common_utils

    cfg = AttrDict(yaml.safe_load((src / "tools/cfgs/dataset_configs/custom_dataset.yaml").read_text()))
    classes = ["Vehicle", "Pedestrian"]
    cfg.MAP_CLASS_TO_KITTI = {"Vehicle": "Car", "Pedestrian": "Pedestrian"}
    sampling = cfg.DATA_AUGMENTOR.AUG_CONFIG_LIST[0]
    sampling.PREPARE = {"filter_by_min_points": ["Vehicle:5", "Pedestrian:5"]}
    sampling.SAMPLE_GROUPS = ["Vehicle:4", "Pedestrian:4"]
    cfg.DATA_PROCESSOR = [p for p in cfg.DATA_PROCESSOR if p.NAME != "transform_points_to_voxels"]
    logger = common_utils.create_logger()
    np.random.seed(0)
    lines = []
    for training in (True, False):
        ds = CustomDataset(cfg, classes, training=training, root_path=root, logger=logger)
        drawn = [ds[i] for i in range(len(ds))]
        shapes = [(d["frame_id"], len(d["gt_boxes"])) for d in drawn]
        lines.append(f"openpcdet CustomDataset {ds.mode}: {len(ds)} frames drawn (frame, boxes): {shapes}")
    for split in ("train", "val"):
        ds.set_split(split)
        ours = {i["point_cloud"]["lidar_idx"]: i for i in pickle.loads((root / f"custom_infos_{split}.pkl").read_bytes())}
        boxed = [x for x in ds.sample_id_list if (root / "labels" / f"{x}.txt").read_text()]  # get_label needs a box
        for theirs in ds.get_infos(classes, num_workers=1, has_label=True, sample_id_list=boxed, num_features=4):
            mine = ours[theirs["point_cloud"]["lidar_idx"]]
            assert mine["point_cloud"] == theirs["point_cloud"] and set(mine["annos"]) == set(theirs["annos"])
            assert mine["annos"]["name"].tolist() == theirs["annos"]["name"].tolist()
            assert mine["annos"]["gt_boxes_lidar"].dtype == theirs["annos"]["gt_boxes_lidar"].dtype
            np.testing.assert_array_equal(mine["annos"]["gt_boxes_lidar"], theirs["annos"]["gt_boxes_lidar"])
        lines.append(f"openpcdet get_infos({split}) on our points/labels == our custom_infos_{split}.pkl ({len(boxed)} frames)")
    return lines


def check_mmdet3d(src: Path, det_root: Path, seg_root: Path) -> list[str]:
    class Table:
        def __init__(self, rows):
            self.table = "\n".join(" ".join(map(str, r)) for r in rows)

    stub("terminaltables", AsciiTable=Table)
    stub("mmcv")
    stub("mmcv.ops", box_iou_rotated=never_called, points_in_boxes_all=never_called, points_in_boxes_part=never_called)
    stub("mmdet"), stub("mmdet.structures"), stub("mmdet.structures.bbox", bbox_overlaps=never_called)
    package("mmdet3d", src / "mmdet3d"), package("mmdet3d.datasets", src / "mmdet3d/datasets")
    utils = package("mmdet3d.utils", src / "mmdet3d/utils")
    sys.path.insert(0, str(src))
    from mmdet3d.utils.array_converter import array_converter

    utils.array_converter = array_converter
    structures = package("mmdet3d.structures", src / "mmdet3d/structures")
    import mmdet3d.structures.bbox_3d as bbox_3d

    structures.__dict__.update({k: getattr(bbox_3d, k) for k in dir(bbox_3d) if not k.startswith("_")})
    from mmdet3d.datasets.kitti_dataset import KittiDataset
    from mmdet3d.datasets.semantickitti_dataset import SemanticKittiDataset

    lines = []
    for split in ("train", "val"):
        ds = KittiDataset(data_root=str(det_root), ann_file=f"kitti_infos_{split}.pkl",
                          data_prefix=dict(pts="training/velodyne"), pipeline=[], filter_empty_gt=False,
                          metainfo=dict(classes=["Pedestrian", "Car"]), modality=dict(use_lidar=True))
        # mmengine's BaseDataset.get_data_info replaces sample_idx by the position in the dataset
        stored = [d["sample_idx"] for d in pickle.loads((det_root / f"kitti_infos_{split}.pkl").read_bytes())["data_list"]]
        worst = 0.0
        for i in range(len(ds)):
            info = ds.get_data_info(i)
            boxes = info["ann_info"]["gt_bboxes_3d"]
            k = stored[i]  # no scan is empty, so export ids are the scan numbers
            ref = np.asarray(SCANS[k][0], np.float32).reshape(-1, 7)
            got = torch.cat([boxes.gravity_center, boxes.dims, boxes.yaw[:, None]], 1).numpy() if len(boxes) else ref[:0]
            diff = got - ref
            diff[:, 6] = (diff[:, 6] + np.pi) % (2 * np.pi) - np.pi
            worst = max([worst, *np.abs(diff).ravel().tolist()])
            names = [["Pedestrian", "Car"][c] for c in info["ann_info"]["gt_labels_3d"].tolist()]
            assert names == SCANS[k][1], (names, SCANS[k][1])
            assert len(np.fromfile(info["lidar_points"]["lidar_path"], np.float32)) == 4 * len(scan_points(k))
        assert worst < 1e-5, worst
        lines.append(f"mmdet3d KittiDataset({split}): {len(ds)} frames, LiDAR boxes back within {worst:.1e}, labels right")
    for split in ("train", "val"):
        ds = SemanticKittiDataset(data_root=str(seg_root), ann_file=f"semantickitti_infos_{split}.pkl", pipeline=[],
                                  metainfo=dict(classes=SemanticKittiDataset.METAINFO["classes"],
                                                seg_label_mapping=MMDET3D_LABELS_MAP, max_label=259), ignore_index=19)
        for i in range(len(ds)):
            info = ds.get_data_info(i)
            raw = np.fromfile(info["pts_semantic_mask_path"], np.int32).astype(np.int64) % 2**16  # its loader
            ours = semantickitti.to_train_ids(raw.astype(np.uint16)).astype(np.int64)
            np.testing.assert_array_equal(info["seg_label_mapping"][raw], np.where(ours == 0, 19, ours - 1))
            assert len(np.fromfile(info["lidar_points"]["lidar_path"], np.float32)) == 4 * len(raw)
        lines.append(f"mmdet3d SemanticKittiDataset({split}): {len(ds)} frames, classes = our train ids - 1")
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--openpcdet", type=Path, help="OpenPCDet source checkout (holds pcdet/ and tools/cfgs/)")
    parser.add_argument("--mmdet3d", type=Path, help="mmdetection3d source checkout (holds mmdet3d/)")
    args = parser.parse_args()
    if not args.openpcdet and not args.mmdet3d:
        parser.error("give --openpcdet and/or --mmdet3d")
    failed = False
    with tempfile.TemporaryDirectory() as tmp:
        exports = make_exports(Path(tmp))
        checks = []
        if args.openpcdet:
            checks.append(("openpcdet", lambda: check_openpcdet(args.openpcdet, exports["openpcdet"])))
        if args.mmdet3d:
            checks.append(("mmdet3d", lambda: check_mmdet3d(args.mmdet3d, exports["mmdet3d-det"], exports["mmdet3d-seg"])))
        for name, check in checks:
            try:
                for line in check():
                    print("PASS", line)
            except Exception as err:  # a check script: report every failure, then exit 1
                failed = True
                print(f"FAIL {name}: {type(err).__name__}: {err}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
