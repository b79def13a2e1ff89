"""The domain builder: apply a scene spec to source scans, record what was drawn,
and write a domain shard.

Every source scan is checked once, at the entry (finite values, intensities in
the sensor's scale; ``omnilidar.domains.point_checks``), naming its file. Only
what the scene calls for is computed: ground is estimated (once, on the source
scan) only when an effect of the scene needs it, effects with zero severity
(``"none"``) or parameters that change nothing (``is_identity``, e.g. zero water)
are skipped, and an empty scene returns the source scan object itself. Warnings
raised while building a scan (e.g. ring recovery falling back to the nominal beam
table) are re-emitted and kept in its record (``"warnings"``). The ground mask follows the points through the effect chain (lost
points leave it, weather returns are not ground).

Every random choice of a scan comes from one generator: the severity of each
effect, its drawn parameters (``draw_params``) and a seed for its ``apply``. The
*record* keeps severities, parameters, fidelity knobs and seeds, so
:func:`rebuild_scan` regenerates the scan bit for bit without the scene spec.
The domain shard seeds each scan with ``SeedSequence([seed, domain id, scan
index])``, so a scan's result does not depend on how the domain is sharded.
"""

from __future__ import annotations

import json
import sys
import warnings
from dataclasses import asdict
from pathlib import Path

import numpy as np

from omnilidar.data.range_image import RangeImageSpec, to_range_image
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec
from omnilidar.domains import ground as ground_estimation
from omnilidar.domains.effects.base import WEATHER_RETURN_LABEL
from omnilidar.domains.point_checks import check_points
from omnilidar.domains.source import LABEL_FORMATS, load_index, read_entry, split_entries
from omnilidar.domains.spec import NO_EFFECT, DomainSpec, SceneSpec, effect_module
from omnilidar.errors import InputError
from omnilidar.io.json_file import read_json
from omnilidar.io import semantickitti
from omnilidar.io.atomic import atomic_path

_MASK_KEYS = ("lost", "changed", "weather")


def scan_rng(seed: int, *keys: int) -> np.random.Generator:
    """The generator of one scan: ``SeedSequence([seed, *keys])`` (e.g. domain id, scan index)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), *(int(k) for k in keys)]))


def _jsonable(value):
    """numpy scalars/arrays and tuples -> plain JSON types (floats keep every bit)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value


def _draw_steps(spec: SceneSpec, rng: np.random.Generator) -> list[dict]:
    steps = []
    for effect in spec.effects:
        severity = effect.draw_severity(rng)
        step = {"name": effect.name, "severity": severity, "params": None, "seed": None,
                "fidelity": dict(effect.fidelity)}
        if severity != NO_EFFECT:
            step["params"] = _jsonable(effect.module.draw_params(severity, rng))
            step["seed"] = int(rng.integers(0, 2**63 - 1))
        steps.append(step)
    return steps


def _is_identity(module, params: dict) -> bool:
    check = getattr(module, "is_identity", None)
    return bool(check(params)) if check is not None else False


def _run_steps(scan: Scan, steps: list[dict], sensor: SensorSpec) -> tuple[Scan, list[dict], bool]:
    """Apply the recorded steps; returns (scan, per-step outcome of the steps with
    params, ground estimated). Steps whose params change nothing are not run."""
    active = [s for s in steps if s["params"] is not None]
    modules = [effect_module(s["name"]) for s in active]
    runs = [not _is_identity(m, s["params"]) for s, m in zip(active, modules)]
    needs_ground = any(m.NEEDS_GROUND and run for m, run in zip(modules, runs))
    ground = ground_estimation.estimate_ground(scan, sensor) if needs_ground else None
    current, outcomes = scan, []
    for step, module, run in zip(active, modules, runs):
        if not run:
            outcomes.append({k: 0 for k in _MASK_KEYS})
            continue
        out, info = module.apply(
            current, step["params"], sensor, np.random.default_rng(step["seed"]),
            ground=ground if module.NEEDS_GROUND else None,
            fidelity=step["fidelity"] or None, return_info=True,
        )
        if ground is not None:
            ground = ground[~info["lost"]] & ~info["weather"]
        outcome = {k: int(np.count_nonzero(info[k])) for k in _MASK_KEYS}
        outcome.update({k: _jsonable(v) for k, v in info.items() if k not in _MASK_KEYS})
        outcomes.append(outcome)
        current = out
    return current, outcomes, needs_ground


def _run_checked(scan: Scan, steps: list[dict], sensor: SensorSpec, source) -> tuple[Scan, list[dict], bool, list[str]]:
    """Check the scan's points once, run the steps, and collect the warnings they
    raise (re-emitted, and returned as messages for the record)."""
    check_points(scan, sensor.intensity_scale, sensor.name, source)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out, outcomes, estimated = _run_steps(scan, steps, sensor)
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    where = f"{source}: " if source is not None else ""
    return out, outcomes, estimated, [where + str(w.message) for w in caught]


def build_scan(scan: Scan, spec: SceneSpec, sensor: SensorSpec, rng: np.random.Generator,
               source: str | Path | None = None) -> tuple[Scan, dict]:
    """Apply a scene spec to one scan (read from ``source``, named in errors and warnings).

    Returns the new scan and its record: ``{"effects": [{name, severity, params,
    seed, fidelity, outcome}], "ground_estimated": bool}`` plus ``"warnings"``
    (messages) when any were raised (JSON-serialisable). An empty spec, or one
    whose every severity is "none", returns ``scan`` itself. InputError (naming
    ``source``) when a point value is non-finite or an intensity is outside the
    sensor's scale.
    """
    steps = _draw_steps(spec, rng)
    out, outcomes, estimated, caught = _run_checked(scan, steps, sensor, source)
    active = [s for s in steps if s["params"] is not None]
    for step, outcome in zip(active, outcomes):
        step["outcome"] = outcome
    record = {"effects": steps, "ground_estimated": estimated}
    if caught:
        record["warnings"] = caught
    return out, record


def rebuild_scan(scan: Scan, record: dict, sensor: SensorSpec, source: str | Path | None = None) -> Scan:
    """Regenerate a built scan from its source scan and its record (sidecar entry)."""
    try:
        steps = [{"name": s["name"], "params": s["params"], "seed": s["seed"], "fidelity": s.get("fidelity") or {}}
                 for s in record["effects"]]
    except (KeyError, TypeError):
        raise InputError(None, "record: needs 'effects' entries with name, params and seed") from None
    return _run_checked(scan, steps, sensor, source)[0]


# ------------------------------------------------------------------ domain shards


def range_image_spec(domain: DomainSpec, settings: dict) -> RangeImageSpec:
    """The domain's image geometry: its sensor's field of view and range limits,
    one row per source beam (unless ``range_image.height`` overrides it)."""
    ri = settings.get("range_image", {})
    return RangeImageSpec.from_sensor(domain.sensor, height=ri.get("height"), width=ri.get("width", 1024))


def write_points_kitti(path: Path, scan: Scan) -> None:
    """float32 x, y, z, intensity ``.bin`` with intensity in 0..1 (KITTI remission
    scale, whatever the sensor's native scale); an empty scan gives an empty file."""
    points = scan.points.copy()
    points[:, 3] = np.clip(points[:, 3] / np.float32(scan.intensity_scale), 0.0, 1.0)
    semantickitti.write_points(path, points)


def _box_record(scan: Scan) -> dict | None:
    if len(scan.boxes) == 0:
        return None
    return {"boxes_lidar": scan.boxes.boxes.tolist(), "names": scan.boxes.names.tolist()}


def build_domain_shard(domain: DomainSpec, index_path: str | Path, shard: int, num_shards: int,
                       settings: dict, seed: int, out: str | Path, progress: bool = True) -> dict:
    """Build shard ``shard`` of ``num_shards`` of a domain into directory ``out``
    (written atomically): ``range/%06d.npz`` (key "image", (2, H, W) float32),
    ``velodyne/%06d.bin``, ``labels/%06d.label`` (when the source has labels) and
    ``sidecar.json``. File numbers are the scans' indices in the source split.
    Points stay in the source's (levelled) frame; the range image projection
    undoes a mount pitch, so rows are beams. Returns the sidecar.
    """
    from tqdm import tqdm

    index = load_index(index_path, domain.dataset)
    entries = split_entries(index, domain.split, index_path)
    indices = domain.scan_indices(len(entries), shard, num_shards)
    sensor = domain.sensor
    spec = range_image_spec(domain, settings)
    sidecar = {
        "domain": domain.name, "label": domain.label, "id": domain.id,
        "dataset": domain.dataset, "split": domain.split, "sensor": domain.sensor_name,
        "shard": shard, "num_shards": num_shards, "seed": seed,
        "range_image": asdict(spec),
        "point_format": "float32 x,y,z,intensity (0..1)",
        "label_format": LABEL_FORMATS[domain.dataset],
        "points_frame": "levelled (z up; see SensorSpec)",
        "weather_return_label": WEATHER_RETURN_LABEL,
        "effects": [{"name": e.name, "severities": list(e.severities), "fidelity": e.fidelity}
                    for e in domain.scene.effects],
        "scans": [],
    }
    with atomic_path(out) as tmp:
        for sub in ("range", "velodyne"):
            (tmp / sub).mkdir(parents=True)
        bar = tqdm(indices, desc=f"{domain.name} shard {shard}/{num_shards}", file=sys.stderr,
                   disable=not progress, mininterval=2.0)
        for i in bar:
            entry = entries[i]
            scan = read_entry(index, entry, sensor)
            built, record = build_scan(scan, domain.scene, sensor, scan_rng(seed, domain.id, i), entry["points"])
            name = f"{i:06d}"
            np.savez(tmp / "range" / f"{name}.npz", image=to_range_image(built, spec))
            write_points_kitti(tmp / "velodyne" / f"{name}.bin", built)
            if built.semantic is not None:
                (tmp / "labels").mkdir(exist_ok=True)
                semantickitti.write_label(tmp / "labels" / f"{name}.label", built.semantic, built.instance)
            sidecar["scans"].append({
                "index": i, "name": name, "source": entry["points"], "source_labels": entry.get("labels"),
                "seed": [seed, domain.id, i], "num_points_in": len(scan), "num_points_out": len(built),
                "boxes": _box_record(built), **record,
            })
        (tmp / "sidecar.json").write_text(json.dumps(sidecar, indent=1))
    return sidecar


def read_sidecar(shard_dir: str | Path) -> dict:
    """A shard's sidecar.json; InputError if missing or not JSON."""
    return read_json(Path(shard_dir) / "sidecar.json", "domain shard sidecar not found (is this a build-domain output?)")
