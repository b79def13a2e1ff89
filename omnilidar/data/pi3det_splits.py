"""Deterministic train/val lists for a Pi3DET platform, split by sequence.

Pi3DET publishes no official split lists (REFERENCE). Until it does, a
platform's frames (every ``<platform>_infos_*.pkl`` in its folder, or the info
files given) are split by sequence so that no sequence is in both lists:

* a frame's sequence is the folder of its point file relative to the dataset
  root, without a final ``velodyne`` component (``drone/seq_03/velodyne/0001.bin``
  -> ``drone/seq_03``);
* sequences are sorted by name and every ``k``-th goes to val, starting with the
  first (positions 0, k, 2k, ...; ``k = 5`` puts 1 in 5 sequences in val);
* frames keep their order; the lists are written as
  ``<platform>/<platform>_infos_{train,val}.pkl`` next to the inputs.

The same inputs and ``k`` always give the same lists.
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath

from omnilidar.errors import InputError

OUTPUT_SPLITS = ("train", "val")


def sequence_of(info: dict) -> str:
    from omnilidar.io.pi3det import POINT_PATH_KEY

    folder = PurePosixPath(str(info[POINT_PATH_KEY]).replace("\\", "/")).parent
    return str(folder.parent if folder.name == "velodyne" else folder)


def default_infos(root: Path, platform: str) -> list[Path]:
    outputs = {f"{platform}_infos_{s}.pkl" for s in OUTPUT_SPLITS}
    return [p for p in sorted((root / platform).glob(f"{platform}_infos_*.pkl")) if p.name not in outputs]


def split_by_sequence(infos: list[dict], every: int) -> tuple[dict[str, list[dict]], dict[str, list[str]]]:
    """``({train, val}: infos, {train, val}: sequences)``."""
    if every < 2:
        raise InputError(None, f"--val-every must be at least 2, got {every}")
    sequences = sorted({sequence_of(i) for i in infos})
    if len(sequences) < 2:
        raise InputError(None, f"all {len(infos)} frames are in one sequence ({sequences[0] if sequences else '-'}); "
                               "a split by sequence needs at least two")
    val = set(sequences[::every])
    lists = {"train": [i for i in infos if sequence_of(i) not in val], "val": [i for i in infos if sequence_of(i) in val]}
    return lists, {"train": [s for s in sequences if s not in val], "val": sorted(val)}


def write_split_lists(root: str | Path, platform: str, every: int = 5, infos_paths: list | None = None,
                      overwrite: bool = False) -> dict[str, list[str]]:
    """Read the platform's infos, split them, write the two lists; returns the sequences per split."""
    from omnilidar.io import pi3det

    root = Path(root)
    paths = [Path(p) for p in infos_paths] if infos_paths else default_infos(root, platform)
    if not paths:
        raise InputError(root / platform, f"no {platform}_infos_*.pkl to split (pass --infos)")
    infos, seen = [], {}
    for path in paths:
        for info in pi3det.read_infos(path):
            frame = str(info["frame_id"])
            if frame in seen:
                raise InputError(path, f"frame {frame!r} is also in {seen[frame]}")
            seen[frame] = path
            infos.append(info)
    lists, sequences = split_by_sequence(infos, every)
    targets = {s: root / platform / f"{platform}_infos_{s}.pkl" for s in OUTPUT_SPLITS}
    for target in targets.values():
        if target.exists() and not overwrite and target not in paths:
            raise InputError(target, "exists; pass --overwrite to replace it")
    for split, target in targets.items():
        pi3det.write_infos(target, lists[split])
    return sequences
