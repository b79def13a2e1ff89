"""Pi3DET frames -> OpenPCDet batch dicts for detection training and evaluation.

A *record* names one frame: ``{"points": path, "boxes": (M, 7) list, "names":
[M], "frame_id": str}``, boxes in the frame's own LiDAR frame (before the
platform shift). Records come from Pi3DET infos (:func:`records_from_infos`),
from subset entries of the dataset index (:func:`records_from_entries`), or
from pseudo-box shards (:mod:`.pseudo_boxes`).

One item, as OpenPCDet's ``prepare_data`` builds it: read x, y, z, intensity;
keep the boxes of the detector's classes; add SHIFT_COOR to points and box
centres; in training augment (:mod:`.augment`) with the generator of (seed,
draw); wrap headings to [-pi, pi); drop points and boxes (by centre) outside
the point cloud range; shuffle points in training; voxelise
(:mod:`.voxelize`). A training draw whose frame keeps no box (OpenPCDet draws
another frame) takes the next frame in order that keeps one, so a batch never
teaches on an empty target set.

:class:`DetCollate` stacks items into the contract's ``batch_dict``:
``points`` (N, 5) with the batch index first, ``voxels``,
``voxel_num_points``, ``voxel_coords`` (V, 4) [b, z, y, x], ``gt_boxes`` (B,
Mmax, 8) with class ids 1..K (zero rows pad), ``batch_size`` and
``frame_id``; tensors are float32 / int32 as OpenPCDet's collate leaves them
after ``load_data_to_gpu``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from omnilidar.downstream.det.augment import augment, limit_heading
from omnilidar.downstream.det.data_config import PlatformConfig
from omnilidar.downstream.det.voxelize import points_to_voxels
from omnilidar.errors import InputError
from omnilidar.io import pi3det, semantickitti


def draw_rng(seed: int, draw: int, purpose: int = 0) -> np.random.Generator:
    """The generator of one training draw: purpose 0 augmentation, 1 point shuffle."""
    return np.random.default_rng([int(seed), 0xDE7, int(purpose), int(draw)])


def records_from_infos(infos: list[dict], root: str | Path) -> list[dict]:
    """Records of validated Pi3DET infos whose point paths are relative to ``root``."""
    out = []
    for info in infos:
        annos = info.get("annos") or {"gt_names": np.zeros(0, str), "gt_boxes_lidar": np.zeros((0, 7), np.float32)}
        out.append({"points": str(Path(root) / info[pi3det.POINT_PATH_KEY]), "frame_id": str(info["frame_id"]),
                    "boxes": np.asarray(annos["gt_boxes_lidar"], np.float32).reshape(-1, 7).tolist(),
                    "names": [str(n) for n in annos["gt_names"]]})
    return out


def records_from_entries(entries: list[dict]) -> list[dict]:
    """Records of Pi3DET dataset-index (or subset) entries (each names its info pickle and position)."""
    cache: dict[str, list[dict]] = {}
    out = []
    for e in entries:
        if "infos" not in e or "info_index" not in e:
            raise InputError(e.get("points"), "index entry is not a Pi3DET frame (no infos / info_index)")
        infos = cache.setdefault(e["infos"], pi3det.read_infos(e["infos"]))
        info = infos[int(e["info_index"])]
        rec = records_from_infos([info], ".")[0]
        rec["points"] = str(e["points"])  # the index resolved it against the dataset root
        out.append(rec)
    return out


def count_boxes(records: list[dict], class_names) -> int:
    return sum(sum(n in class_names for n in r["names"]) for r in records)


class DetScanDataset(torch.utils.data.Dataset):
    """Frames of one platform, indexed by ``(draw, i)`` (training) or ``i`` (evaluation)."""

    def __init__(self, records: list[dict], cfg: PlatformConfig, voxels: dict, augmentation: dict | None = None,
                 seed: int = 0):
        self.records = list(records)
        self.cfg = cfg
        self.voxels = voxels  # {max_points_per_voxel, max_voxels_train, max_voxels_test}
        self.augmentation = augmentation
        self.seed = int(seed)

    def __len__(self) -> int:
        return len(self.records)

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points (N, 4), boxes (M, 7) and class ids (M,) 1..K of frame ``i``, shifted, not yet filtered."""
        rec = self.records[i]
        points = semantickitti.read_points(rec["points"])
        if len(points) == 0:
            raise InputError(rec["points"], "scan has 0 points")
        if not np.isfinite(points).all():
            raise InputError(rec["points"], "scan holds NaN or infinite values")
        boxes = np.asarray(rec["boxes"], np.float32).reshape(-1, 7)
        keep = np.array([n in self.cfg.class_names for n in rec["names"]], bool)
        boxes = boxes[keep]
        labels = np.array([self.cfg.class_names.index(n) + 1 for n, k in zip(rec["names"], keep) if k], np.int64)
        shift = np.asarray(self.cfg.shift, np.float32)
        points = points.copy()
        points[:, :3] += shift
        boxes[:, :3] += shift
        return points, boxes, labels

    def _prepared(self, i: int, draw: int | None) -> dict | None:
        points, boxes, labels = self.frame(i)
        if draw is not None and self.augmentation is not None:
            points, boxes = augment(points, boxes, self.augmentation, draw_rng(self.seed, draw))
        boxes[:, 6] = limit_heading(boxes[:, 6])
        pcr = np.asarray(self.cfg.point_cloud_range, np.float32)
        in_range = np.all((points[:, :3] >= pcr[:3]) & (points[:, :3] <= pcr[3:]), axis=1)
        points = points[in_range]
        centre_in = np.all((boxes[:, :3] >= pcr[:3]) & (boxes[:, :3] <= pcr[3:]), axis=1)
        boxes, labels = boxes[centre_in], labels[centre_in]
        if draw is not None:
            if len(boxes) == 0:
                return None
            points = points[draw_rng(self.seed, draw, purpose=1).permutation(len(points))]
        cap = self.voxels["max_voxels_train" if draw is not None else "max_voxels_test"]
        voxels, coords, num = points_to_voxels(points, self.cfg.voxel_size, self.cfg.point_cloud_range,
                                               self.voxels["max_points_per_voxel"], cap)
        return {"points": points, "voxels": voxels, "voxel_coords": coords, "voxel_num_points": num,
                "gt_boxes": np.concatenate([boxes, labels[:, None].astype(np.float32)], axis=1),
                "frame_id": self.records[i]["frame_id"], "index": i}

    def __getitem__(self, key) -> dict:
        draw, i = key if isinstance(key, tuple) else (None, key)
        for step in range(len(self.records)):
            item = self._prepared((i + step) % len(self.records), draw)
            if item is not None:
                return item
        raise InputError(self.records[i]["points"], f"no training frame keeps a {'/'.join(self.cfg.class_names)} "
                                                    f"box inside the point cloud range; nothing to train on")


class DetCollate:
    """Items -> the contract's ``batch_dict`` of torch tensors (``None`` for fast-forwarded batches)."""

    def __call__(self, items: list[dict]) -> dict | None:
        if not items:
            return None
        points, coords = [], []
        for b, it in enumerate(items):
            points.append(np.concatenate([np.full((len(it["points"]), 1), b, np.float32), it["points"]], axis=1))
            coords.append(np.concatenate([np.full((len(it["voxel_coords"]), 1), b, np.int32), it["voxel_coords"]], axis=1))
        most = max(1, max(len(it["gt_boxes"]) for it in items))
        gt = np.zeros((len(items), most, 8), np.float32)
        for b, it in enumerate(items):
            gt[b, :len(it["gt_boxes"])] = it["gt_boxes"]
        return {
            "batch_size": len(items),
            "points": torch.from_numpy(np.concatenate(points)),
            "voxels": torch.from_numpy(np.concatenate([it["voxels"] for it in items])),
            "voxel_num_points": torch.from_numpy(np.concatenate([it["voxel_num_points"] for it in items])),
            "voxel_coords": torch.from_numpy(np.concatenate(coords)),
            "gt_boxes": torch.from_numpy(gt),
            "frame_id": [it["frame_id"] for it in items],
            "index": [it["index"] for it in items],
        }


def batch_to(batch: dict, device) -> dict:
    """The batch with its tensors on ``device`` (voxel coordinates as int32, the rest float32)."""
    return {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}
