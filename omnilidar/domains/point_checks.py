"""The one check of a scan's point values before effects run on it.

Every effect works in physical units (reflectance = intensity / the sensor's
scale), so a non-finite value or an intensity outside the sensor's scale (a
0..255 file fed to a 0..1 sensor, negative values) would be silently clipped or
amplified. The domain builder checks each source scan once, at its entry,
naming the file; effects called on their own run the same check.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnilidar.lidar.scan import Scan
from omnilidar.errors import InputError


def check_points(scan: Scan, scale: float, scale_owner: str, source: str | Path | None = None, who: str = "") -> None:
    """InputError (naming ``source``, prefixed by ``who``) unless every coordinate
    and intensity is finite and every intensity lies in 0..``scale`` (the
    intensity unit of ``scale_owner``: the domain's sensor, or the scan itself)."""
    prefix = f"{who}: " if who else ""
    pts = scan.points
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        raise InputError(source, f"{prefix}{int(bad.sum())} of {len(pts)} points have NaN or infinite coordinates "
                                 f"or intensities (first at index {int(np.argmax(bad))})")
    if len(pts) == 0:
        return
    scale = float(scale)
    low, high = float(pts[:, 3].min()), float(pts[:, 3].max())
    if low < 0.0 or high > scale:
        raise InputError(source, f"{prefix}intensities span {low:g}..{high:g}, outside the {scale_owner} scale "
                                 f"0..{scale:g} (a file in another intensity unit?)")


def effect_scale(scan: Scan, sensor, who: str) -> float:
    """What every effect's ``apply`` does before it computes: the builder's check of the points
    against the sensor's intensity scale, the one scale every effect works in. Returns it."""
    scale = float(sensor.intensity_scale)
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(None, f"{who}: sensor {sensor.name!r} needs a positive intensity scale, got {scale}")
    check_points(scan, scale, sensor.name, who=who)
    return scale
