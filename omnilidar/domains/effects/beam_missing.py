"""Beam missing (SemanticKITTI-C / Robo3D): whole laser rings return nothing.

Robo3D drops a fixed number of randomly chosen beams of the 64 per scan
(16 / 32 / 48 on SemanticKITTI for light / moderate / heavy). We keep those
severities as fractions of the sensor's beams, 0.25 / 0.5 / 0.75, so the same
severity means the same loss on a 32-beam sensor. The beams are drawn per scan
without replacement from the ``rng`` handed to :func:`apply` (so the builder's
recorded seed regenerates them) and reported in the info dict
(``dropped_beams``), which the builder copies into the sidecar.

Differences from the anchor: rings come from ring recovery
(``omnilidar.data.rings``: the file's firing order only when it checks out,
else a per-scan calibration of the beam lines; ``ring_method`` in the info
dict) instead of counting azimuth wraps unchecked, which breaks on any scan
not stored ring by ring; point
order and labels are kept (dropped points take their labels with them).
"""

from __future__ import annotations

import numpy as np

from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import SensorSpec
from omnilidar.domains.effects.beam_reduction import (
    DEFAULT_FIDELITY,
    FIDELITY_LEVELS,
    HIGHEST_FIDELITY,
    fidelity_calibrates,
    drop_rings,
    scan_rings,
)
from omnilidar.domains.effects.beam_reduction import accuracy_time_curve as _ring_curve
from omnilidar.domains.effects.base import unchanged
from omnilidar.domains.point_checks import effect_scale
from omnilidar.errors import InputError

NEEDS_GROUND = False

SEVERITIES: dict[str, dict] = {
    "light": {"drop_fraction": 0.25},
    "moderate": {"drop_fraction": 0.5},
    "heavy": {"drop_fraction": 0.75},
}

__all__ = ["NEEDS_GROUND", "SEVERITIES", "DEFAULT_FIDELITY", "FIDELITY_LEVELS", "HIGHEST_FIDELITY",
           "draw_params", "apply", "accuracy_time_curve"]


def draw_params(severity: str, rng: np.random.Generator) -> dict:
    """The severity's fraction of beams to drop (the beams themselves are drawn in apply)."""
    if severity not in SEVERITIES:
        raise InputError(None, f"beam_missing: unknown severity {severity!r}; known: {', '.join(SEVERITIES)}")
    return dict(SEVERITIES[severity])


def _fraction(params: dict) -> float:
    if not isinstance(params, dict) or set(params) != {"drop_fraction"}:
        raise InputError(None, f"beam_missing: params must be {{'drop_fraction': float}}, got {params!r}")
    try:
        f = float(params["drop_fraction"])
    except (TypeError, ValueError):
        raise InputError(None, f"beam_missing: drop_fraction must be a number, got {params['drop_fraction']!r}") from None
    if not (np.isfinite(f) and 0.0 <= f <= 1.0):
        raise InputError(None, f"beam_missing: drop_fraction must be in [0, 1], got {f}")
    return f


def apply(scan: Scan, params: dict, sensor: SensorSpec, rng: np.random.Generator, *,
          ground: np.ndarray | None = None, fidelity: dict | None = None, return_info: bool = False):
    """Drop ``round(drop_fraction * num_beams)`` beams chosen at random.

    ``drop_fraction = 0`` returns the input itself. With ``return_info`` also
    returns {"lost", "changed", "weather", "ring_method", "dropped_beams" (sorted list)}.
    """
    del ground
    f = _fraction(params)
    calibrate = fidelity_calibrates(fidelity)
    count = int(round(f * sensor.num_beams))
    if count == 0 or len(scan) == 0:
        return (scan, {**unchanged(scan, True)[1], "dropped_beams": []}) if return_info else scan
    effect_scale(scan, sensor, "beam_missing")
    dropped = np.sort(rng.choice(sensor.num_beams, size=count, replace=False))
    keep = np.ones(sensor.num_beams, bool)
    keep[dropped] = False
    rings, method = scan_rings(scan, sensor, calibrate)
    result = drop_rings(scan, rings, keep, return_info, method)
    if not return_info:
        return result
    out, info = result
    return out, {**info, "dropped_beams": [int(b) for b in dropped]}


def accuracy_time_curve(scan: Scan, sensor: SensorSpec, severity: str, seeds, repeats: int = 1) -> list[dict]:
    """Same knob as beam reduction (ring recovery calibration); errors are the
    fraction of points whose ring differs from the calibrated recovery."""
    rows = _ring_curve(scan, sensor, "half", seeds, repeats)
    for row in rows:
        row["severity"] = severity
        row.pop("err_keep_mismatch", None)
    return rows
