"""The nuScenes release (devkit tables) converted to our nuScenes layout.

A release is ``<dataroot>/<version>/*.json`` (``scene``, ``sample``,
``sample_data``, ``calibrated_sensor``, ``sensor``, ``lidarseg``), point files
``<dataroot>/samples/LIDAR_TOP/*.pcd.bin`` and lidarseg labels
``<dataroot>/lidarseg/<version>/<sample_data token>_lidarseg.bin``. The tables
are read as JSON directly (the ``nuscenes-devkit`` package pins numpy < 2 and
pulls OpenCV, so it is not a dependency): a scene's samples, each sample's
LIDAR_TOP key frame (``sample_data`` whose calibrated sensor's channel is
LIDAR_TOP and ``is_key_frame``), its ``lidarseg`` entry by
``sample_data_token``.

Splits come from the devkit's official scene lists, ``nuscenes/utils/splits.py``
(``train`` / ``val`` for v1.0-trainval, ``mini_train`` / ``mini_val`` for
v1.0-mini), read as literals from that file -- the installed devkit's, or one
given by path -- never imported. Scenes in neither list (the test split) are
skipped.

Output (docs/datasets.md): ``<out>/<split>/samples/LIDAR_TOP/<name>.pcd.bin``
and ``<out>/<split>/lidarseg/<name>_lidarseg.bin``, linked (absolute symlinks)
or copied, written atomically.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from omnilidar.errors import InputError

CHANNEL = "LIDAR_TOP"
RECORD_BYTES = 20  # float32 x, y, z, intensity, ring
SPLIT_LISTS = {"v1.0-mini": {"train": "mini_train", "val": "mini_val"},
               "v1.0-trainval": {"train": "train", "val": "val"}}


@dataclass(frozen=True)
class Frame:
    split: str
    scene: str
    timestamp: int
    points: Path
    lidarseg: Path | None

    @property
    def name(self) -> str:
        return self.points.name[: -len(".pcd.bin")]


def devkit_splits_file() -> Path | None:
    """``nuscenes/utils/splits.py`` of an installed devkit (found, not imported)."""
    spec = importlib.util.find_spec("nuscenes")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(next(iter(spec.submodule_search_locations))) / "utils" / "splits.py"
    return path if path.is_file() else None


def read_split_lists(path: str | Path) -> dict[str, list[str]]:
    """Every ``name = [scene names]`` literal assigned at the top of a devkit splits file."""
    path = Path(path)
    try:
        tree = ast.parse(path.read_text(), str(path))
    except (OSError, SyntaxError, UnicodeDecodeError) as err:
        raise InputError(path, f"not a readable devkit splits file: {err}") from None
    lists = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name) \
                and isinstance(node.value, ast.List):
            try:
                value = ast.literal_eval(node.value)
            except ValueError:
                continue
            if all(isinstance(v, str) for v in value):
                lists[node.targets[0].id] = value
    return lists


def read_table(tables: Path, name: str) -> list[dict]:
    path = tables / f"{name}.json"
    if not path.is_file():
        raise InputError(path, f"nuScenes table {name}.json not found")
    try:
        rows = json.loads(path.read_text())
    except ValueError as err:
        raise InputError(path, f"not JSON: {err}") from None
    if not isinstance(rows, list) or not all(isinstance(r, dict) and "token" in r for r in rows):
        raise InputError(path, "expected a list of records with a 'token'")
    return rows


def _need(row: dict, key: str, table: Path):
    if key not in row:
        raise InputError(table, f"record {row.get('token')!r} lacks {key!r}")
    return row[key]


def plan_frames(tables: str | Path, split_lists: dict[str, list[str]], version: str | None = None) -> list[Frame]:
    """Every LIDAR_TOP key frame of a train or val scene, by scene and time."""
    tables = Path(tables)
    version = version or tables.name
    if version not in SPLIT_LISTS:
        raise InputError(tables, f"unknown nuScenes version {version!r} (known: {', '.join(SPLIT_LISTS)}); "
                                 "pass --version")
    wanted = {}
    for split, list_name in SPLIT_LISTS[version].items():
        if list_name not in split_lists:
            raise InputError(None, f"the splits file has no list {list_name!r} for {version}")
        wanted.update({scene: split for scene in split_lists[list_name]})
    dataroot = tables.parent
    scenes = {r["token"]: _need(r, "name", tables / "scene.json") for r in read_table(tables, "scene")}
    samples = {r["token"]: _need(r, "scene_token", tables / "sample.json") for r in read_table(tables, "sample")}
    sensors = {r["token"]: r.get("channel") for r in read_table(tables, "sensor")}
    calibrated = {r["token"]: sensors.get(r.get("sensor_token")) for r in read_table(tables, "calibrated_sensor")}
    lidarseg = {_need(r, "sample_data_token", tables / "lidarseg.json"): _need(r, "filename", tables / "lidarseg.json")
                for r in (read_table(tables, "lidarseg") if (tables / "lidarseg.json").is_file() else [])}
    frames = []
    table = tables / "sample_data.json"
    for row in read_table(tables, "sample_data"):
        if calibrated.get(_need(row, "calibrated_sensor_token", table)) != CHANNEL or not row.get("is_key_frame"):
            continue
        sample = _need(row, "sample_token", table)
        if sample not in samples or samples[sample] not in scenes:
            raise InputError(table, f"record {row['token']!r}: sample {sample!r} or its scene is not in the tables")
        scene = scenes[samples[sample]]
        if scene not in wanted:
            continue
        filename = _need(row, "filename", table)
        if not filename.endswith(".pcd.bin"):
            raise InputError(table, f"record {row['token']!r}: {filename!r} is not a .pcd.bin lidar sweep")
        seg = lidarseg.get(row["token"])
        frames.append(Frame(wanted[scene], scene, int(_need(row, "timestamp", table)), dataroot / filename,
                            dataroot / seg if seg else None))
    if not frames:
        raise InputError(tables, "no LIDAR_TOP key frames of a train or val scene found")
    return sorted(frames, key=lambda f: (f.split, f.scene, f.timestamp))


def check_frame(frame: Frame) -> None:
    """Point file present and whole; lidarseg holds one label per point."""
    if not frame.points.is_file():
        raise InputError(frame.points, "lidar sweep named in sample_data.json not found")
    size = frame.points.stat().st_size
    if size == 0 or size % RECORD_BYTES:
        raise InputError(frame.points, f"{size} bytes is not a whole number of {RECORD_BYTES}-byte points")
    if frame.lidarseg is not None:
        if not frame.lidarseg.is_file():
            raise InputError(frame.lidarseg, "lidarseg file named in lidarseg.json not found")
        if frame.lidarseg.stat().st_size != size // RECORD_BYTES:
            raise InputError(frame.lidarseg, f"has {frame.lidarseg.stat().st_size} labels but its sweep "
                                             f"{frame.points.name} has {size // RECORD_BYTES} points")


def write_layout(frames: list[Frame], out: str | Path, copy: bool = False) -> dict:
    """Link or copy the frames into our layout at ``out`` (atomically); counts per split."""
    from omnilidar.io.atomic import atomic_path

    for frame in frames:
        check_frame(frame)
    counts: dict[str, dict[str, int]] = {}
    with atomic_path(out) as tmp:
        for frame in frames:
            scans = tmp / frame.split / "samples" / CHANNEL
            labels = tmp / frame.split / "lidarseg"
            scans.mkdir(parents=True, exist_ok=True)
            pairs = [(frame.points, scans / frame.points.name)]
            if frame.lidarseg is not None:
                labels.mkdir(parents=True, exist_ok=True)
                pairs.append((frame.lidarseg, labels / f"{frame.name}_lidarseg.bin"))
            for src, dst in pairs:
                if dst.exists():
                    raise InputError(src, f"two key frames map to {dst.name}")
                if copy:
                    shutil.copyfile(src, dst)
                else:
                    os.symlink(src.resolve(), dst)
            c = counts.setdefault(frame.split, {"scans": 0, "labelled": 0})
            c["scans"] += 1
            c["labelled"] += frame.lidarseg is not None
    return counts
