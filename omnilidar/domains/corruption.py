"""SemanticKITTI-C-style corrupted evaluation sets (after Robo3D).

Four corruptions of the validation split, each at three severities, written as
``<out>/sequences/<seq>/{velodyne,labels}`` (the SemanticKITTI layout, frame
names of the source kept, so ``omnilidar.io.semantickitti`` and external tools
read them) plus ``sidecar.json`` with every scan's drawn parameters and seeds.

==============  ==============  ===============================================
corruption      effect          severities light / moderate / heavy
==============  ==============  ===============================================
fog             fog             backscatter 0.008 / 0.05 / 0.2 1/(m sr);
                                attenuation drawn per scan from
                                {0, 0.005, 0.01, 0.02, 0.03, 0.06} 1/m
wet_ground      wet_ground      water 0.2 / 1.0 / 1.2 mm, noise floor 0.3 / 0.3 / 0.7
snow            snow            0.5 mm/h at 2.0 m/s / 1.0 at 1.6 / 2.5 at 1.6
beam_missing    beam_missing    25 / 50 / 75 % of the beams dropped at random per
                                scan (Robo3D: 16 / 32 / 48 of 64 on KITTI)
==============  ==============  ===============================================

Severity is fixed within a set (as in SemanticKITTI-C), unlike the GDA domains
where it is drawn per scan. The severities are the effect modules' own presets;
the table repeats them for reference. Seeds: ``SeedSequence([seed,
CORRUPTION_STREAM, corruption id, severity id, scan index])``, independent of the
domain builder's streams.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from omnilidar.domains.builder import build_scan, scan_rng, write_points_kitti
from omnilidar.domains.source import load_index, read_entry, split_entries
from omnilidar.domains.spec import EffectSpec, SceneSpec
from omnilidar.errors import InputError
from omnilidar.io import semantickitti
from omnilidar.io.atomic import atomic_path
from omnilidar.lidar.sensors import get_sensor

# corruption name -> effect module name (EFFECTS in spec.py)
CORRUPTIONS: dict[str, str] = {
    "fog": "fog",
    "wet_ground": "wet_ground",
    "snow": "snow",
    "beam_missing": "beam_missing",
}
SEVERITIES = ("light", "moderate", "heavy")
CORRUPTION_STREAM = 0xC0  # keeps these seeds apart from the domains' (seed, domain id, index)


def corruption_scene(corruption: str, severity: str, fidelity: dict | None = None) -> SceneSpec:
    """The one-effect, fixed-severity scene of a corrupted set."""
    if corruption not in CORRUPTIONS:
        raise InputError(None, f"unknown corruption {corruption!r}; known: {', '.join(CORRUPTIONS)}")
    if severity not in SEVERITIES:
        raise InputError(None, f"unknown severity {severity!r}; known: {', '.join(SEVERITIES)}")
    return SceneSpec((EffectSpec(CORRUPTIONS[corruption], (severity,), fidelity or {}),))


def build_corrupted_set(corruption: str, severity: str, index_path: str | Path, settings: dict,
                        seed: int, out: str | Path, progress: bool = True) -> dict:
    """Write one corrupted set from ``settings`` (the ``domains.corrupted`` section:
    dataset, split, sensor, max_scans, fidelity per effect) into ``out``, atomically.
    Returns the sidecar."""
    from tqdm import tqdm

    scene = corruption_scene(corruption, severity, settings.get("fidelity", {}).get(CORRUPTIONS[corruption]))
    dataset = settings.get("dataset", "semantickitti")
    index = load_index(index_path, dataset)
    entries = split_entries(index, settings.get("split", "val"), index_path)
    max_scans = settings.get("max_scans")
    entries = entries if max_scans is None else entries[:max_scans]
    if not entries:
        raise InputError(index_path, f"split {settings.get('split', 'val')!r} has no scans to corrupt")
    sensor = get_sensor(settings.get("sensor", "kitti_hdl64e"))
    c_id, s_id = list(CORRUPTIONS).index(corruption), SEVERITIES.index(severity)
    sidecar = {"corruption": corruption, "severity": severity, "effect": CORRUPTIONS[corruption],
               "dataset": dataset, "split": settings.get("split", "val"), "sensor": sensor.name, "seed": seed,
               "point_format": "float32 x,y,z,remission (0..1)", "scans": []}
    with atomic_path(out) as tmp:
        bar = tqdm(list(enumerate(entries)), desc=f"{corruption}/{severity}", file=sys.stderr,
                   disable=not progress, mininterval=2.0)
        for i, entry in bar:
            scan = read_entry(index, entry, sensor)
            built, record = build_scan(scan, scene, sensor, scan_rng(seed, CORRUPTION_STREAM, c_id, s_id, i),
                                       entry["points"])
            seq = str(entry.get("sequence", "08"))
            frame = str(entry.get("frame", f"{i:06d}"))
            seq_dir = tmp / "sequences" / seq
            (seq_dir / "velodyne").mkdir(parents=True, exist_ok=True)
            write_points_kitti(seq_dir / "velodyne" / f"{frame}.bin", built)
            if built.semantic is not None:
                (seq_dir / "labels").mkdir(exist_ok=True)
                semantickitti.write_label(seq_dir / "labels" / f"{frame}.label", built.semantic, built.instance)
            sidecar["scans"].append({
                "index": i, "sequence": seq, "frame": frame, "source": entry["points"],
                "source_labels": entry.get("labels"), "seed": [seed, CORRUPTION_STREAM, c_id, s_id, i],
                "num_points_in": len(scan), "num_points_out": len(built), **record,
            })
        (tmp / "sidecar.json").write_text(json.dumps(sidecar, indent=1))
    return sidecar
