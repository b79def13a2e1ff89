"""What the synthetic world writes, known from its settings alone: the shard names of each dataset
(as the workflow names them), which Pi3DET scenes go to val, and how many scans each split will
hold. Light to import (no ray casting), so the workflow can plan from it before any scan exists;
omnilidar.data.synthetic.export writes the shards."""

from __future__ import annotations

from omnilidar.errors import InputError
from omnilidar.io import kitti360, semantickitti

DATASETS = ("semantickitti", "kitti360", "pi3det", "nuscenes")
SEMANTICKITTI_TEST = tuple(f"{i:02d}" for i in range(11, 22))


def shard_names(dataset: str, settings: dict) -> list[str]:
    """Shard names configured for ``dataset`` (as the workflow names them)."""
    spec = settings["datasets"][dataset]
    if dataset == "semantickitti":
        return [f"{int(s):02d}" for s in spec["sequences"]]
    if dataset == "kitti360":
        return [f"{int(s):04d}" for s in spec["sequences"]]
    if dataset == "pi3det":
        return list(spec["platforms"])
    if dataset == "nuscenes":
        return list(spec["splits"])
    raise InputError(None, f"unknown synthetic dataset {dataset!r}; known: {', '.join(DATASETS)}")


def shard_settings(settings: dict, dataset: str, shard: str) -> dict:
    """The part of the synthetic section one shard is made from: every shared key (world,
    radiometry, ...) and, of ``datasets``, only this shard's own entry (its sequence, Pi3DET
    platform or nuScenes split). The workflow keys a shard's provenance on it, so a change to
    another dataset, platform or sequence leaves this shard as it is."""
    spec = dict(settings["datasets"][dataset])
    if dataset in ("semantickitti", "kitti360"):
        names = shard_names(dataset, settings)
        spec["sequences"] = [s for s, name in zip(spec["sequences"], names) if name == shard]
    elif dataset == "pi3det":
        spec["platforms"] = {shard: spec["platforms"][shard]}
    else:
        spec["splits"] = {shard: spec["splits"][shard]}
    return {**settings, "datasets": {dataset: spec}}


def pi3det_val_scenes(spec: dict) -> int:
    """Scenes of a Pi3DET platform that go to val (the last ones): val_fraction of them, at least one
    where the fraction is positive and at least one scene is left for train."""
    n_scenes = spec["scenes"]
    n_val = int(round(spec["val_fraction"] * n_scenes))
    if n_scenes > 1:
        n_val = min(max(n_val, 1 if spec["val_fraction"] > 0 else 0), n_scenes - 1)
    return n_val


def planned_split_counts(dataset: str, settings: dict) -> dict[str, int]:
    """{split: scans} the configured world will hold once written, keyed as its index names the
    splits (omnilidar.data.index), so a workflow can plan from it before any scan exists."""
    spec = settings["datasets"][dataset]
    shards = set(shard_names(dataset, settings))
    if dataset == "semantickitti":
        per = {s: spec["scans_per_test_sequence"] if s in SEMANTICKITTI_TEST else spec["scans_per_sequence"]
               for s in shards}
        return {split: sum(per.get(seq, 0) for seq in seqs) for split, seqs in semantickitti.SPLITS.items()}
    if dataset == "kitti360":
        return {split: spec["scans_per_sequence"] * sum(f"{seq:04d}" in shards for seq in seqs)
                for split, seqs in kitti360.SPLITS.items()}
    if dataset == "pi3det":
        counts = {}
        for platform, p in spec["platforms"].items():
            n_val = pi3det_val_scenes(p)
            counts[f"{platform}_train"] = (p["scenes"] - n_val) * p["scans_per_scene"]
            counts[f"{platform}_val"] = n_val * p["scans_per_scene"]
        return counts
    return {split: s["scenes"] * s["scans_per_scene"] for split, s in spec["splits"].items()}
