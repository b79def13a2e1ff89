"""mmdet3d 1.x SemanticKITTI segmentation infos (tools/dataset_converters/semantickitti_converter.py,
mmdet3d/datasets/semantickitti_dataset.py and seg3d_dataset.py, mmdetection3d v1.4).

::

    ROOT/sequences/00/velodyne/<id>.bin   train scans, float32 x, y, z, intensity (SemanticKITTI layout)
    ROOT/sequences/00/labels/<id>.label   uint32 raw SemanticKITTI ids (semantic | instance << 16)
    ROOT/sequences/08/...                 val scans and labels (SemanticKITTI's val sequence)
    ROOT/semantickitti_infos_{train,val}.pkl
        {'metainfo': {'DATASET': 'SemanticKITTI'},
         'data_list': [{'lidar_points': {'lidar_path': 'sequences/00/velodyne/<id>.bin', 'num_pts_feats': 4},
                        'pts_semantic_mask_path': 'sequences/00/labels/<id>.label',
                        'sample_id': '<id>'}, ...]}
        as get_semantickitti_info writes them (paths relative to the data root).

Labels stay raw SemanticKITTI ids, exactly as the pseudo-labeller wrote them: mmdet3d's
SemanticKITTI config reads ``.label`` as int32 (seg_3d_dtype), keeps ``label % 2**16``
(seg_offset) and maps raw ids to its 19 classes with the ``labels_map`` of
configs/_base_/datasets/semantickitti.py (unlabelled and ignored ids -> 19). That map
is the official learning map with our train ids shifted down by one (our train id 0,
ignore, is its 19), so the export needs no relabelling and stays readable by
SemanticKITTI tools too.
"""

from __future__ import annotations

import pickle
from pathlib import Path

from omnilidar.io.export.frames import ExportFrame, load_labels, split_names

NUM_PTS_FEATS = 4
SEQUENCE = {"train": "00", "val": "08"}


def relative_paths(frame: ExportFrame) -> tuple[str, str]:
    seq = f"sequences/{SEQUENCE[frame.split]}"
    return f"{seq}/velodyne/{frame.name}.bin", f"{seq}/labels/{frame.name}.label"


def frame_info(frame: ExportFrame) -> dict:
    points, labels = relative_paths(frame)
    return {"lidar_points": {"lidar_path": points, "num_pts_feats": NUM_PTS_FEATS},
            "pts_semantic_mask_path": labels, "sample_id": frame.name}


def write(root: Path, planned: list[ExportFrame]) -> dict:
    """Write scans, labels and the info files under ``root``; return counts per split."""
    for seq in SEQUENCE.values():
        (root / "sequences" / seq / "velodyne").mkdir(parents=True)
        (root / "sequences" / seq / "labels").mkdir(parents=True)
    for frame in planned:
        points = frame.points()
        labels = load_labels(frame.source, len(points))
        points_rel, labels_rel = relative_paths(frame)
        points.tofile(root / points_rel)
        labels.tofile(root / labels_rel)
    summary = {}
    for split, frames in split_names(planned).items():
        infos = {"metainfo": {"DATASET": "SemanticKITTI"}, "data_list": [frame_info(f) for f in frames]}
        with open(root / f"semantickitti_infos_{split}.pkl", "wb") as fh:
            pickle.dump(infos, fh)
        summary[split] = {"frames": len(frames)}
    return summary
