"""OpenPCDet custom-dataset layout (pcdet/datasets/custom/custom_dataset.py, OpenPCDet v0.6).

::

    ROOT/points/<id>.npy             float32 (N, 4) x, y, z, intensity (CustomDataset.get_lidar: np.load)
    ROOT/labels/<id>.txt             one box a line: "x y z dx dy dz heading name" (get_label; the
                                     tutorial's label template), z at the box centre, name Car / Pedestrian
    ROOT/ImageSets/{train,val}.txt   ids, one a line, in the same order as the infos (__getitem__ takes
                                     frame_id = sample_id_list[index] for infos[index])
    ROOT/custom_infos_{train,val}.pkl  list of {'point_cloud': {'num_features': 4, 'lidar_idx': id},
                                     'annos': {'name': (M,) str array, 'gt_boxes_lidar': (M, 7) float32}}
                                     as create_custom_infos / get_infos writes them
    ROOT/gt_database/<id>_<name>_<i>.bin, ROOT/custom_dbinfos_train.pkl
                                     what create_groundtruth_database writes for the gt_sampling
                                     augmentation of custom_dataset.yaml: the points inside each train
                                     box, relative to its centre, and {name: [{'name', 'path', 'gt_idx',
                                     'box3d_lidar', 'num_points_in_gt'}]}; every exported class has a
                                     key, an empty list when no train box has it (the sampler reads
                                     infos[name] for each of the config's classes)

So a user can train at once (``python train.py --cfg_file ...``) without rerunning
``create_custom_infos``; rerunning it on this layout writes the same infos, except for
frames without boxes, which its get_label cannot read (an empty label file gives a
(0,) array); ours carry (0, 7) boxes and (0,) names.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from omnilidar.io.export.frames import ExportFrame, inside_boxes, split_names

NUM_FEATURES = 4


def number_text(value: float) -> str:
    """Shortest decimal text that reads back as the same float32."""
    return np.format_float_positional(np.float32(value), unique=True, trim="-")


def label_lines(boxes: np.ndarray, names: tuple[str, ...]) -> str:
    return "".join(" ".join(number_text(v) for v in box) + f" {name}\n" for box, name in zip(boxes, names))


def frame_info(frame: ExportFrame) -> dict:
    boxes = frame.boxes
    return {
        "point_cloud": {"num_features": NUM_FEATURES, "lidar_idx": frame.name},
        "annos": {"name": np.array(frame.box_names, dtype=str).reshape(-1),
                  "gt_boxes_lidar": np.asarray(boxes, np.float32).reshape(-1, 7)},
    }


def _database_entries(root: Path, frame: ExportFrame, points: np.ndarray) -> list[dict]:
    """Write the points of each box of a train frame under gt_database/; return their db infos."""
    boxes, names = frame.boxes, frame.box_names
    if len(boxes) == 0:
        return []
    inside = inside_boxes(points, boxes)
    entries = []
    for i, (box, name) in enumerate(zip(boxes, names)):
        local = points[inside[:, i]].copy()
        local[:, :3] -= box[:3]
        rel = f"gt_database/{frame.name}_{name}_{i}.bin"
        local.astype(np.float32).tofile(root / rel)
        entries.append({"name": name, "path": rel, "gt_idx": i, "box3d_lidar": box.astype(np.float32),
                        "num_points_in_gt": int(len(local))})
    return entries


def write(root: Path, planned: list[ExportFrame]) -> dict:
    """Write the layout under ``root`` (an empty directory); return counts per split."""
    for folder in ("points", "labels", "ImageSets", "gt_database"):
        (root / folder).mkdir(parents=True)
    # every exported class gets a key, also one with no train box: the samplers index them by class name
    database: dict[str, list[dict]] = {name: [] for frame in planned for name in frame.box_names}
    for frame in planned:
        points = frame.points()
        np.save(root / "points" / f"{frame.name}.npy", points)
        (root / "labels" / f"{frame.name}.txt").write_text(label_lines(frame.boxes, frame.box_names))
        if frame.split == "train":
            for entry in _database_entries(root, frame, points):
                database.setdefault(entry["name"], []).append(entry)
    summary = {}
    for split, frames in split_names(planned).items():
        (root / "ImageSets" / f"{split}.txt").write_text("".join(f"{f.name}\n" for f in frames))
        with open(root / f"custom_infos_{split}.pkl", "wb") as fh:
            pickle.dump([frame_info(f) for f in frames], fh)
        summary[split] = {"frames": len(frames), "boxes": int(sum(len(f.boxes) for f in frames))}
    with open(root / "custom_dbinfos_train.pkl", "wb") as fh:
        pickle.dump(database, fh)
    summary["gt_database"] = {name: len(v) for name, v in sorted(database.items())}
    return summary
