"""Beam reduction (the Beam-32 domain): keep every k-th laser ring of a scan.

A thin effect around :func:`omnilidar.data.rings.beam_reduce` with the effect
interface of ``base.py``, so a scene spec can list it beside the weather effects.
Rings come from ``scan.ring`` when the reader provides them (nuScenes, the
synthetic world before export) and from ring recovery otherwise (KITTI ``.bin``
files carry no ring, but are stored in firing order): the info dict says which
method found them (``ring_method``, copied into the domain sidecar), and a
fallback to the nominal beam table warns. Kept points stay in input order with their
labels; ``keep_every = 1`` returns the input itself.

Severities: ``half`` keeps even ring ids (64 -> 32 beams, the paper's Beam-32),
``quarter`` keeps every fourth ring (64 -> 16).

The numerical knob is ring recovery itself: ``calibrate`` (firing order, else
per-scan Hough calibration of the beam angles and laser offsets, the default)
against nominal data-sheet binning; the accuracy/time curve measures how many points change ring
(and so change keep/drop) without calibration, and what calibration costs.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from omnilidar.data.rings import recover_rings, ring_recovery
from omnilidar.domains.effects.base import unchanged
from omnilidar.domains.point_checks import effect_scale
from omnilidar.errors import InputError
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec

NEEDS_GROUND = False

SEVERITIES: dict[str, dict] = {
    "half": {"keep_every": 2},
    "quarter": {"keep_every": 4},
}

DEFAULT_FIDELITY: dict = {"calibrate": True}
FIDELITY_LEVELS: dict[str, list] = {"calibrate": [False, True]}
HIGHEST_FIDELITY: dict = {"calibrate": True}


def draw_params(severity: str, rng: np.random.Generator) -> dict:
    """The severity's ring stride (fixed; ``rng`` is not used)."""
    if severity not in SEVERITIES:
        raise InputError(None, f"beam_reduction: unknown severity {severity!r}; known: {', '.join(SEVERITIES)}")
    return dict(SEVERITIES[severity])


def _keep_every(params: dict) -> int:
    if not isinstance(params, dict) or set(params) != {"keep_every"}:
        raise InputError(None, f"beam_reduction: params must be {{'keep_every': int}}, got {params!r}")
    k = params["keep_every"]
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise InputError(None, f"beam_reduction: keep_every must be a positive integer, got {k!r}")
    return int(k)


def fidelity_calibrates(fidelity: dict | None) -> bool:
    fid = {**DEFAULT_FIDELITY, **(fidelity or {})}
    unknown = set(fid) - set(DEFAULT_FIDELITY)
    if unknown:
        raise InputError(None, f"beam_reduction: unknown fidelity knobs {sorted(unknown)}")
    return bool(fid["calibrate"])


def scan_rings(scan: Scan, sensor: SensorSpec, calibrate: bool = True) -> tuple[np.ndarray, str]:
    """Ring id per point and how it was found: the scan's own rings ("scan") when
    present, else :func:`omnilidar.data.rings.ring_recovery`."""
    if scan.ring is not None:
        return scan.ring, "scan"
    return ring_recovery(scan.points, sensor, calibrate=calibrate)


def drop_rings(scan: Scan, rings: np.ndarray, keep: np.ndarray, return_info: bool, method: str | None = None):
    """Keep the points whose ring is selected by ``keep`` (bool per ring id);
    points with an unknown ring (-1) are dropped. Rings follow the kept points.
    The info dict carries ``ring_method`` when ``method`` is given."""
    known = (rings >= 0) & (rings < len(keep))
    mask = np.zeros(len(scan), bool)
    mask[known] = keep[rings[known]]
    out = replace(scan, ring=rings).select(mask)
    if not return_info:
        return out
    info = {"lost": ~mask, "changed": np.zeros(len(scan), bool), "weather": np.zeros(len(out), bool)}
    if method is not None:
        info["ring_method"] = method
    return out, info


def apply(scan: Scan, params: dict, sensor: SensorSpec, rng: np.random.Generator, *,
          ground: np.ndarray | None = None, fidelity: dict | None = None, return_info: bool = False):
    """Keep rings whose id is a multiple of ``params["keep_every"]``.

    ``ground`` and ``rng`` are unused. With ``return_info`` also returns
    {"lost": (N_in,), "changed": (N_in,) all False, "weather": (N_out,) all False,
    "ring_method": see :func:`scan_rings`}.
    """
    del ground, rng
    k = _keep_every(params)
    calibrate = fidelity_calibrates(fidelity)
    if k == 1 or len(scan) == 0:
        return unchanged(scan, return_info)
    effect_scale(scan, sensor, "beam_reduction")
    rings, method = scan_rings(scan, sensor, calibrate)
    keep = np.arange(sensor.num_beams) % k == 0
    return drop_rings(scan, rings, keep, return_info, method)


def accuracy_time_curve(scan: Scan, sensor: SensorSpec, severity: str, seeds, repeats: int = 1) -> list[dict]:
    """Ring recovery without and with calibration: time per scan and the fraction
    of points whose keep/drop decision (and ring) differs from the calibrated one.

    Deterministic, so ``seeds`` only sets how many timing repeats are taken.
    The scan's own rings, if any, are ignored (the knob is ring recovery).
    """
    params = draw_params(severity, np.random.default_rng(0))
    k = params["keep_every"]
    bare = replace(scan, ring=None)
    n_runs = max(1, len(list(seeds))) * max(1, repeats)

    def run(calibrate: bool):
        times = []
        for _ in range(n_runs):
            t0 = time.perf_counter()
            rings = recover_rings(bare.points, sensor, calibrate=calibrate)
            times.append(time.perf_counter() - t0)
        return float(np.median(times)), rings

    _, ref = run(True)
    ref_keep = (ref >= 0) & (ref % k == 0)
    rows = []
    for value in FIDELITY_LEVELS["calibrate"]:
        t, rings = run(value)
        keep = (rings >= 0) & (rings % k == 0)
        n = max(len(scan), 1)
        rows.append({
            "severity": severity, "knob": "calibrate", "value": value, "time_s": t,
            "err_keep_mismatch": float(np.count_nonzero(keep != ref_keep) / n),
            "err_ring_mismatch": float(np.count_nonzero(rings != ref) / n),
        })
    return rows
