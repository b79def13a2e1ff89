"""Write synthetic shards in the real datasets' on-disk layouts.

One call writes one shard directory, built in a temporary sibling and renamed
into place (:func:`omnilidar.io.atomic.atomic_path`), so an interrupted job
leaves nothing behind:

* ``semantickitti``, shard "NN": ``sequences/NN`` with ``velodyne/%06d.bin`` and
  (sequences 00-10 only, as in the real dataset) ``labels/%06d.label``;
* ``kitti360``, shard = sequence number: ``data_3d_raw/2013_05_28_drive_%04d_sync``
  with ``velodyne_points/data/%010d.bin``;
* ``pi3det``, shard = platform: ``<platform>/velodyne/<frame_id>.bin``,
  ``labels/<frame_id>.label`` (ground-truth semantics) and
  ``<platform>_infos_{train,val}.pkl`` (paths relative to the dataset root);
* ``nuscenes``, shard = split: ``<split>/samples/LIDAR_TOP/<name>.pcd.bin``
  (x, y, z, intensity 0..255, ring) and ``<split>/lidarseg/<name>_lidarseg.bin``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from omnilidar.data.synthetic import classes as C
from omnilidar.data.synthetic.sequence import shard_entropy, simulate_sequence
from omnilidar.data.synthetic.shards import DATASETS, SEMANTICKITTI_TEST, pi3det_val_scenes, shard_names
from omnilidar.errors import InputError
from omnilidar.io.atomic import atomic_path
from omnilidar.lidar.scan import Boxes


# SemanticKITTI raw id -> nuScenes-lidarseg general class index (0..31).
# nuScenes general classes used: 0 noise, 2 human.pedestrian.adult, 14 vehicle.bicycle,
# 16 vehicle.bus.rigid, 17 vehicle.car, 21 vehicle.motorcycle, 23 vehicle.truck,
# 24 flat.driveable_surface, 25 flat.other, 26 flat.sidewalk, 27 flat.terrain,
# 28 static.manmade, 30 static.vegetation. A ridden bicycle and its rider are one
# nuScenes bicycle (the rider is inside the bicycle's box).
NUSCENES_GENERAL: dict[int, int] = {
    0: 0, C.CAR: 17, C.BICYCLE: 14, C.MOTORCYCLE: 21, C.TRUCK: 23, C.OTHER_VEHICLE: 16,
    C.PERSON: 2, C.BICYCLIST: 14, C.MOTORCYCLIST: 21,
    C.ROAD: 24, C.PARKING: 24, C.SIDEWALK: 26, C.OTHER_GROUND: 25, C.TERRAIN: 27,
    C.BUILDING: 28, C.FENCE: 28, C.POLE: 28, C.TRAFFIC_SIGN: 28,
    C.VEGETATION: 30, C.TRUNK: 30,
}
_NUSC_LUT = np.zeros(1 << 16, np.uint8)
for _raw, _nus in NUSCENES_GENERAL.items():
    _NUSC_LUT[_raw] = _nus


def to_nuscenes_general(semantic: np.ndarray) -> np.ndarray:
    """Raw SemanticKITTI ids -> nuScenes-lidarseg general class ids (uint8); unknown -> 0 (noise)."""
    return _NUSC_LUT[np.asarray(semantic, dtype=np.uint16)]


def _progress(total: int, desc: str):
    return tqdm(total=total, desc=desc, unit="scan", file=sys.stderr, disable=total <= 1, leave=False)


def _check_shard(dataset: str, shard: str, settings: dict) -> str:
    names = shard_names(dataset, settings)
    if dataset in ("semantickitti", "kitti360") and shard.isdigit():
        shard = f"{int(shard):02d}" if dataset == "semantickitti" else f"{int(shard):04d}"
    if shard not in names:
        raise InputError(None, f"shard {shard!r} of {dataset} is not configured in synthetic.datasets.{dataset} "
                               f"(configured: {', '.join(names)})")
    return shard


def write_shard(dataset: str, shard: str, settings: dict, seed: int, out: str | Path) -> dict:
    """Generate and write one shard into directory ``out`` (atomically).

    ``settings`` is the validated ``synthetic`` section. Returns a small summary
    (scans written, points, boxes).
    """
    if dataset not in DATASETS:
        raise InputError(None, f"unknown synthetic dataset {dataset!r}; known: {', '.join(DATASETS)}")
    shard = _check_shard(dataset, str(shard), settings)
    entropy = shard_entropy(seed, dataset, shard)
    writer = {"semantickitti": _semantickitti, "kitti360": _kitti360, "pi3det": _pi3det, "nuscenes": _nuscenes}[dataset]
    out = Path(out)
    with atomic_path(out) as tmp:
        tmp.mkdir(parents=True)
        summary = writer(shard, settings, entropy, tmp)
    return {"dataset": dataset, "shard": shard, **summary}


def _semantickitti(shard: str, settings: dict, entropy, folder: Path) -> dict:
    from omnilidar.io import semantickitti

    spec = settings["datasets"]["semantickitti"]
    test = shard in SEMANTICKITTI_TEST
    n = spec["scans_per_test_sequence"] if test else spec["scans_per_sequence"]
    (folder / "velodyne").mkdir()
    if not test:
        (folder / "labels").mkdir()
    _, scans = simulate_sequence(settings, entropy, 0, spec["sensor"], "vehicle", n, spec["scan_spacing_m"])
    points = 0
    with _progress(n, f"semantickitti {shard}") as bar:
        for j, scan in enumerate(scans):
            label = None if test else folder / "labels" / f"{j:06d}.label"
            semantickitti.write_scan(scan, folder / "velodyne" / f"{j:06d}.bin", label)
            points += len(scan)
            bar.update()
    return {"scans": n, "points": points, "labelled": not test}


def _kitti360(shard: str, settings: dict, entropy, folder: Path) -> dict:
    from omnilidar.io import kitti360

    spec = settings["datasets"]["kitti360"]
    seq = int(shard)
    n = spec["scans_per_sequence"]
    drive = kitti360.sequence_dir(Path("."), seq).parent  # relative: data_3d_raw/<drive>/velodyne_points
    _, scans = simulate_sequence(settings, entropy, 0, spec["sensor"], "vehicle", n, spec["scan_spacing_m"])
    points = 0
    with _progress(n, f"kitti360 {shard}") as bar:
        for j, scan in enumerate(scans):
            rel = kitti360.scan_path(Path("."), seq, j).relative_to(drive.parent)
            path = folder / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            kitti360.write_scan(scan, path)
            points += len(scan)
            bar.update()
    return {"scans": n, "points": points}


def _pi3det(shard: str, settings: dict, entropy, folder: Path) -> dict:
    from omnilidar.io import pi3det, semantickitti

    spec = settings["datasets"]["pi3det"]["platforms"][shard]
    platform_name = {"vehicle": "Vehicle", "drone": "Drone", "quadruped": "Quadruped"}[shard]
    allowed = pi3det.PLATFORM_CLASSES[platform_name]
    (folder / "velodyne").mkdir()
    (folder / "labels").mkdir()
    n_scenes, per = spec["scenes"], spec["scans_per_scene"]
    n_val = pi3det_val_scenes(spec)
    if spec.get("pedestrians_per_100m") is not None:  # the platform's own crowd density
        settings = {**settings, "world": {**settings["world"], "pedestrians_per_100m": spec["pedestrians_per_100m"]}}
    infos = {"train": [], "val": []}
    points = boxes = 0
    with _progress(n_scenes * per, f"pi3det {shard}") as bar:
        for k in range(n_scenes):
            split = "val" if k >= n_scenes - n_val else "train"
            _, scans = simulate_sequence(settings, entropy, k, spec["sensor"], shard, per, spec["scan_spacing_m"])
            for j, scan in enumerate(scans):
                frame_id = f"{k:02d}{j:04d}"
                semantickitti.write_scan(scan, folder / "velodyne" / f"{frame_id}.bin",
                                         folder / "labels" / f"{frame_id}.label")
                keep = np.isin(scan.boxes.names, allowed)
                kept: Boxes = scan.boxes.select(keep)
                infos[split].append(pi3det.make_info(frame_id, platform_name, f"{shard}/velodyne/{frame_id}.bin", kept))
                points += len(scan)
                boxes += len(kept)
                bar.update()
    for split, items in infos.items():
        pi3det.write_infos(folder / f"{shard}_infos_{split}.pkl", items)
    return {"scans": n_scenes * per, "points": points, "boxes": boxes,
            "train": len(infos["train"]), "val": len(infos["val"])}


def _nuscenes(shard: str, settings: dict, entropy, folder: Path) -> dict:
    from omnilidar.io import nuscenes

    spec = settings["datasets"]["nuscenes"]
    split = spec["splits"][shard]
    samples = folder / "samples" / "LIDAR_TOP"
    segs = folder / "lidarseg"
    samples.mkdir(parents=True)
    segs.mkdir()
    n_scenes, per = split["scenes"], split["scans_per_scene"]
    points = 0
    base_time = 1532402927647951  # microseconds, nuScenes-style timestamps
    with _progress(n_scenes * per, f"nuscenes {shard}") as bar:
        for k in range(n_scenes):
            _, scans = simulate_sequence(settings, entropy, k, spec["sensor"], "vehicle", per, spec["scan_spacing_m"])
            for j, scan in enumerate(scans):
                name = f"n{k:03d}-synthetic-{shard}__LIDAR_TOP__{base_time + k * 10**8 + j * 500_000}"
                nuscenes.write_scan(scan, samples / f"{name}.pcd.bin")
                nuscenes.write_lidarseg(segs / f"{name}_lidarseg.bin", to_nuscenes_general(scan.semantic))
                points += len(scan)
                bar.update()
    return {"scans": n_scenes * per, "points": points}


__all__ = ["write_shard", "shard_names", "to_nuscenes_general", "NUSCENES_GENERAL", "DATASETS"]
