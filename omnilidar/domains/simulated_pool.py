"""Simulated augmentation, the natural baseline for a generator: a pool of real labelled scans
(``make-subset --exclude``) run through a domain's scene by the domain builder, labels carried."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from omnilidar.domains.builder import _jsonable, build_scan, scan_rng, write_points_kitti
from omnilidar.domains.source import load_index, read_entry
from omnilidar.domains.spec import DomainSpec
from omnilidar.errors import InputError
from omnilidar.io import semantickitti
from omnilidar.io.atomic import atomic_path

SIMULATED_POOL_STREAM = 0x51  # keeps these seeds apart from the domains' and the corrupted sets'


def simulate_pool(domain: DomainSpec, index_path: str | Path, pool_path: str | Path, seed: int,
                  out: str | Path, progress: bool = True) -> dict:
    """The domain builder's version of a pool of real labelled scans (``make-subset --exclude``):
    each scan through the domain's scene, labels carried (weather returns get
    WEATHER_RETURN_LABEL, ignored in training), written atomically as ``out/velodyne``,
    ``out/labels`` and ``out/pool.json``, a pool of the simulated scans that train-segmentor
    reads like the real one. Returns that pool document."""
    from tqdm import tqdm

    from omnilidar.downstream.seg.subsets import read_subset, write_subset
    from omnilidar.manifest import digest, file_sha256

    pool = read_subset(pool_path)
    index = load_index(index_path, domain.dataset)
    if pool["dataset"] != domain.dataset:
        raise InputError(pool_path, f"is a pool of {pool['dataset']} scans; domain {domain.name} builds "
                                    f"{domain.dataset} scans")
    sensor = domain.sensor
    out = Path(out)
    entries, records = [], []
    with atomic_path(out) as tmp:
        (tmp / "velodyne").mkdir(parents=True)
        (tmp / "labels").mkdir()
        for k, entry in enumerate(tqdm(pool["entries"], desc=f"{domain.name} pool", file=sys.stderr,
                                       disable=not progress, mininterval=2.0)):
            if not entry.get("labels"):
                raise InputError(entry["points"], "pool scan has no label file to carry")
            scan = read_entry(index, entry, sensor)
            built, record = build_scan(scan, domain.scene, sensor,
                                       scan_rng(seed, SIMULATED_POOL_STREAM, domain.id, k), entry["points"])
            name = f"{k:06d}"
            write_points_kitti(tmp / "velodyne" / f"{name}.bin", built)
            semantickitti.write_label(tmp / "labels" / f"{name}.label", built.semantic, built.instance)
            # The files' digests make pool.json's own digest (what trainers key their resumable
            # state by) change whenever a simulated scan does, e.g. after an effect's code changed.
            entries.append({"points": str(out / "velodyne" / f"{name}.bin"),
                            "labels": str(out / "labels" / f"{name}.label"), "source": entry["points"],
                            "sha256": [file_sha256(tmp / "velodyne" / f"{name}.bin"),
                                       file_sha256(tmp / "labels" / f"{name}.label")]})
            records.append({"name": name, "source": entry["points"], "num_points_in": len(scan),
                            "num_points_out": len(built), "seed": [seed, SIMULATED_POOL_STREAM, domain.id, k],
                            **record})
        doc = {**pool, "entries": entries, "simulated": {"domain": domain.name, "from_pool": str(pool_path),
                                                         "pool_digest": digest(pool_path), "seed": seed}}
        write_subset(doc, tmp / "pool.json")
        (tmp / "sidecar.json").write_text(json.dumps({"domain": domain.name, "scans": _jsonable(records)}, indent=1))
    return doc
