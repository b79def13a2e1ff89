"""mmdet3d 1.x KITTI detection infos (info_version 1.1: tools/dataset_converters/update_infos_to_v2.py
update_kitti_infos, read by mmdet3d/datasets/kitti_dataset.py and det3d_dataset.py, mmdetection3d v1.4).

::

    ROOT/training/velodyne/<id>.bin    float32 x, y, z, intensity (data_prefix pts='training/velodyne')
    ROOT/kitti_infos_{train,val}.pkl   {'metainfo': {'categories', 'dataset': 'kitti', 'info_version': '1.1'},
                                        'data_list': [data info, ...]}
    ROOT/kitti_gt_database/<id>_<name>_<i>.bin, ROOT/kitti_dbinfos_train.pkl
                                       the ObjectSample database of the train split, as
                                       tools/dataset_converters/create_gt_database.py writes it: each
                                       box's points relative to its bottom centre, and {name: [{'name',
                                       'path', 'image_idx', 'gt_idx', 'box3d_lidar' (bottom centre, float32),
                                       'num_points_in_gt', 'difficulty', 'group_id', 'score'}]}, a key
                                       for every exported class

A data info holds ``sample_idx`` (int: the export id; mmengine's BaseDataset.get_data_info
replaces it by the position in the dataset, which KittiMetric indexes by), ``lidar_points`` {num_pts_feats, lidar_path
(file name only, as update_kitti_infos keeps), Tr_velo_to_cam, Tr_imu_to_velo}, ``images``
{CAM2: {cam2img, lidar2cam, lidar2img}, R0_rect} and ``instances``.

KittiDataset.parse_ann_info reads ``bbox_3d`` as CameraInstance3DBoxes and converts it to
the LiDAR frame with inv(images.CAM2.lidar2cam), so boxes are stored in KITTI's camera
convention: the scans have no camera, and lidar2cam is the bare axis change of KITTI's
rectified camera (x = -y_lidar, y = -z_lidar, z = x_lidar, no offset), R0_rect and the
camera matrix are identities. Each box becomes, as OpenPCDet's
transform_annotations_to_kitti_format converts LiDAR boxes for its KITTI evaluation:
bottom centre in that frame, dimensions (l, h, w) = (dx, dz, dy), rotation_y = -heading - pi/2
(wrapped to [-pi, pi)), alpha = rotation_y + atan2(y, x). ``bbox_label_3d`` and ``bbox_label``
index KittiDataset.METAINFO['classes'] (what Det3DDataset's label_mapping expects): Car 2,
Pedestrian 0. The 2D ``bbox`` is [0, 0, 50, 50] with truncated 0, occluded 0 and difficulty 0,
OpenPCDet's placeholder that makes every box "easy" in KITTI evaluation, as Pi3DET
evaluates. No image, image size or ``cam_instances`` are written (monocular fields); mmdet3d's
KittiMetric keeps only predictions inside the camera image, so evaluate these scans with
``omnilidar`` or OpenPCDet's evaluator instead.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from omnilidar.errors import InputError
from omnilidar.io.export.frames import ExportFrame, inside_boxes, split_names
from omnilidar.io.kitti_object import wrap_angle

# KittiDataset.METAINFO['classes'] order; update_kitti_infos writes it as metainfo['categories'].
KITTI_CLASSES = ("Pedestrian", "Cyclist", "Car", "Van", "Truck", "Person_sitting", "Tram", "Misc")
NUM_PTS_FEATS = 4
LIDAR_TO_CAMERA = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
PLACEHOLDER_2D_BOX = [0.0, 0.0, 50.0, 50.0]


def camera_boxes(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """LiDAR boxes (M, 7) -> (KITTI camera boxes (M, 7) [x, y, z bottom centre, l, h, w, ry], alpha (M,)), float64."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    bottom = np.column_stack([b[:, 0], b[:, 1], b[:, 2] - 0.5 * b[:, 5], np.ones(len(b))])
    location = (bottom @ LIDAR_TO_CAMERA.T)[:, :3]
    ry = wrap_angle(-b[:, 6] - 0.5 * np.pi)
    alpha = wrap_angle(ry + np.arctan2(b[:, 1], b[:, 0]))
    return np.column_stack([location, b[:, 3], b[:, 5], b[:, 4], ry]), alpha


def instances(boxes: np.ndarray, names: tuple[str, ...], inside: np.ndarray, where) -> list[dict]:
    """The ``instances`` of one frame (plain Python values, as update_kitti_infos stores them)."""
    unknown = sorted(set(names) - set(KITTI_CLASSES))
    if unknown:
        raise InputError(where, f"class names {unknown} have no KITTI class")
    if len(boxes) == 0:
        return []
    cam, alpha = camera_boxes(boxes)
    counts = inside.sum(0).tolist()
    out = []
    for i, name in enumerate(names):
        label = KITTI_CLASSES.index(name)
        out.append({
            "bbox": list(PLACEHOLDER_2D_BOX), "bbox_label": label, "bbox_3d": cam[i].tolist(), "bbox_label_3d": label,
            "truncated": 0.0, "occluded": 0, "alpha": float(alpha[i]), "score": 0.0, "index": i, "group_id": i,
            "difficulty": 0, "num_lidar_pts": int(counts[i]),
        })
    return out


def database_entries(root: Path, frame: ExportFrame, points: np.ndarray, inside: np.ndarray,
                     group_start: int) -> list[dict]:
    """Write each box's points under kitti_gt_database/; return their db infos (group ids from ``group_start``)."""
    boxes, names = frame.boxes, frame.box_names
    if len(boxes) == 0:
        return []
    bottom = boxes.astype(np.float32).copy()
    bottom[:, 2] -= 0.5 * bottom[:, 5]  # mmdet3d LiDAR boxes sit on their bottom centre
    entries = []
    for i, name in enumerate(names):
        local = points[inside[:, i]].copy()
        local[:, :3] -= bottom[i, :3]
        rel = f"kitti_gt_database/{frame.name}_{name}_{i}.bin"
        local.astype(np.float32).tofile(root / rel)
        entries.append({"name": name, "path": rel, "image_idx": frame.index, "gt_idx": i, "box3d_lidar": bottom[i],
                        "num_points_in_gt": int(len(local)), "difficulty": np.int64(0), "group_id": group_start + i,
                        "score": np.float64(0.0)})
    return entries


def frame_info(frame: ExportFrame, inside: np.ndarray) -> dict:
    identity = np.eye(4).tolist()
    return {
        "sample_idx": frame.index,
        "images": {"CAM2": {"cam2img": identity, "lidar2cam": LIDAR_TO_CAMERA.tolist(),
                            "lidar2img": LIDAR_TO_CAMERA.tolist()},  # cam2img @ lidar2cam
                   "R0_rect": identity},
        "lidar_points": {"num_pts_feats": NUM_PTS_FEATS, "lidar_path": f"{frame.name}.bin",
                         "Tr_velo_to_cam": LIDAR_TO_CAMERA.tolist(), "Tr_imu_to_velo": identity},
        "instances": instances(frame.boxes, frame.box_names, inside, frame.source.points),
    }


def metainfo() -> dict:
    return {"categories": {name: i for i, name in enumerate(KITTI_CLASSES)}, "dataset": "kitti", "info_version": "1.1"}


def write(root: Path, planned: list[ExportFrame]) -> dict:
    """Write scans and info files under ``root``; return counts per split."""
    (root / "training" / "velodyne").mkdir(parents=True)
    (root / "kitti_gt_database").mkdir()
    infos, groups = {}, 0
    # every exported class gets a key, also one with no train box: the samplers index them by class name
    database: dict[str, list[dict]] = {name: [] for frame in planned for name in frame.box_names}
    for frame in planned:
        points = frame.points()
        points.tofile(root / "training" / "velodyne" / f"{frame.name}.bin")
        inside = inside_boxes(points, frame.boxes)
        infos[frame.index] = frame_info(frame, inside)
        if frame.split == "train":
            for entry in database_entries(root, frame, points, inside, groups):
                database.setdefault(entry["name"], []).append(entry)
            groups += len(frame.boxes)
    summary = {}
    for split, frames in split_names(planned).items():
        with open(root / f"kitti_infos_{split}.pkl", "wb") as fh:
            pickle.dump({"metainfo": metainfo(), "data_list": [infos[f.index] for f in frames]}, fh)
        summary[split] = {"frames": len(frames), "boxes": int(sum(len(f.boxes) for f in frames))}
    with open(root / "kitti_dbinfos_train.pkl", "wb") as fh:
        pickle.dump(database, fh)
    summary["gt_database"] = {name: len(v) for name, v in sorted(database.items())}
    return summary
