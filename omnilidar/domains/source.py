"""Source scans of a domain: one entry of a dataset index (``omnilidar.data.index``)
read into a :class:`Scan` with its labels (and boxes, for Pi3DET).

Frames: scans stay in the gravity-levelled frame they are stored in (the project's
convention, see ``SensorSpec``); range images and ring recovery undo a mount pitch
themselves.

Labels: SemanticKITTI and Pi3DET-style ``.label`` files give raw SemanticKITTI
ids; nuScenes lidarseg gives its own class ids 0..31 (carried in ``semantic`` as
they are; the sidecar records the label format).
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache
from pathlib import Path

from omnilidar.data.index import read_index
from omnilidar.errors import InputError
from omnilidar.io import kitti360, nuscenes, pi3det, semantickitti
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec

LABEL_FORMATS = {
    "semantickitti": "semantickitti_raw",
    "kitti360": None,
    "pi3det": "semantickitti_raw",
    "nuscenes": "nuscenes_lidarseg",
}


@lru_cache(maxsize=8)
def _infos(path: str) -> tuple[dict, ...]:
    return tuple(pi3det.read_infos(path))


def split_entries(index: dict, split: str, where: str | Path | None = None) -> list[dict]:
    """The entries of one split of a dataset index; InputError naming the known splits."""
    splits = index.get("splits", {})
    if split not in splits:
        raise InputError(where, f"{index.get('dataset', 'dataset')} index has no split {split!r}; "
                                f"known: {', '.join(splits) or 'none'}")
    return splits[split]


def load_index(path: str | Path, dataset: str | None = None) -> dict:
    """Read a dataset index and check it is the expected dataset's."""
    index = read_index(path)
    if dataset is not None and index.get("dataset") != dataset:
        raise InputError(path, f"is an index of {index.get('dataset')!r}, this domain needs {dataset!r}")
    return index


def read_entry(index: dict, entry: dict, sensor: SensorSpec) -> Scan:
    """Read one indexed scan (points, labels, boxes) in the sensor's intensity scale."""
    dataset = index["dataset"]
    points, labels = entry["points"], entry.get("labels")
    if dataset == "semantickitti":
        return semantickitti.read_scan(points, labels)
    if dataset == "kitti360":
        return kitti360.read_scan(points)
    if dataset == "nuscenes":
        scan = nuscenes.read_scan(points)
        if labels is None:
            return scan
        return replace(scan, semantic=nuscenes.read_lidarseg(labels, len(scan)))
    if dataset == "pi3det":
        info = _infos(str(entry["infos"]))[int(entry["info_index"])]
        scan = pi3det.read_scan(info, index["root"], intensity_scale=sensor.intensity_scale)
        if labels is None:
            return scan
        semantic, instance = semantickitti.read_label(labels, num_points=len(scan))
        return replace(scan, semantic=semantic, instance=instance)
    raise InputError(None, f"unknown dataset {dataset!r} in index")

