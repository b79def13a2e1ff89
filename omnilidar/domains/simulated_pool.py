"""Pools of real labelled scans (``make-subset --exclude``) transformed with their labels carried:

- simulated: run through a domain's scene by the domain builder, the natural baseline for a generator;
- round trip: through the domain's range image and back, what a perfect generator of that image
  size would give (the decomposition's resolution link).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from omnilidar.data.range_image import round_trip
from omnilidar.data.subsets import read_subset, write_subset
from omnilidar.domains.builder import _jsonable, build_scan, range_image_spec, scan_rng, write_points_kitti
from omnilidar.domains.source import load_index, read_entry
from omnilidar.domains.spec import DomainSpec
from omnilidar.errors import InputError
from omnilidar.io import semantickitti
from omnilidar.io.atomic import atomic_path
from omnilidar.manifest import digest, file_sha256

SIMULATED_POOL_STREAM = 0x51  # keeps these seeds apart from the domains' and the corrupted sets'


def simulate_pool(domain: DomainSpec, index_path: str | Path, pool_path: str | Path, seed: int,
                  out: str | Path, progress: bool = True) -> dict:
    """The domain builder's version of a pool of real labelled scans (``make-subset --exclude``):
    each scan through the domain's scene, labels carried (weather returns get
    WEATHER_RETURN_LABEL, ignored in training), written atomically as ``out/velodyne``,
    ``out/labels`` and ``out/pool.json``, a pool of the simulated scans that train-segmentor
    reads like the real one. Returns that pool document."""
    sensor = domain.sensor

    def simulate(scan, k, source):
        built, record = build_scan(scan, domain.scene, sensor,
                                   scan_rng(seed, SIMULATED_POOL_STREAM, domain.id, k), source)
        return built, {"seed": [seed, SIMULATED_POOL_STREAM, domain.id, k], **record}

    return _transformed_pool(domain, index_path, pool_path, out, simulate, "simulated",
                             {"domain": domain.name, "seed": seed}, progress)


def round_trip_pool(domain: DomainSpec, settings: dict, index_path: str | Path, pool_path: str | Path,
                    out: str | Path, progress: bool = True) -> dict:
    """A pool of real labelled scans through the domain's range image and back
    (:func:`omnilidar.data.range_image.round_trip`): what a perfect generator of this image
    size would give, each point with its true label. Written like :func:`simulate_pool`."""
    from dataclasses import asdict

    spec = range_image_spec(domain, settings)

    def trip(scan, k, source):
        return round_trip(scan, spec), {}

    return _transformed_pool(domain, index_path, pool_path, out, trip, "round_trip",
                             {"domain": domain.name, "range_image": asdict(spec)}, progress)


def _transformed_pool(domain: DomainSpec, index_path, pool_path, out, transform, kind: str, about: dict,
                      progress: bool) -> dict:
    """Each pool scan through ``transform(scan, k, source) -> (scan, record)``, labels carried, written
    atomically as ``out/velodyne``, ``out/labels``, ``out/pool.json`` (the pool document, with
    ``kind`` describing how it was made) and ``out/sidecar.json``."""
    from tqdm import tqdm

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
        for k, entry in enumerate(tqdm(pool["entries"], desc=f"{domain.name} pool ({kind})", file=sys.stderr,
                                       disable=not progress, mininterval=2.0)):
            if not entry.get("labels"):
                raise InputError(entry["points"], "pool scan has no label file to carry")
            scan = read_entry(index, entry, sensor)
            built, record = transform(scan, k, entry["points"])
            name = f"{k:06d}"
            write_points_kitti(tmp / "velodyne" / f"{name}.bin", built)
            semantickitti.write_label(tmp / "labels" / f"{name}.label", built.semantic, built.instance)
            # The files' digests make pool.json's own digest (what trainers key their resumable
            # state by) change whenever a transformed scan does, e.g. after an effect's code changed.
            entries.append({"points": str(out / "velodyne" / f"{name}.bin"),
                            "labels": str(out / "labels" / f"{name}.label"), "source": entry["points"],
                            "sha256": [file_sha256(tmp / "velodyne" / f"{name}.bin"),
                                       file_sha256(tmp / "labels" / f"{name}.label")]})
            records.append({"name": name, "source": entry["points"], "num_points_in": len(scan),
                            "num_points_out": len(built), **record})
        doc = {**pool, "entries": entries, kind: {**about, "from_pool": str(pool_path),
                                                  "pool_digest": digest(pool_path)}}
        write_subset(doc, tmp / "pool.json")
        (tmp / "sidecar.json").write_text(json.dumps({"domain": domain.name, kind: about, "scans": _jsonable(records)},
                                                     indent=1))
    return doc
