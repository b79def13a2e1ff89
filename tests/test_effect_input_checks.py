"""Effects called on their own run the builder's point checks, against the sensor's scale."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from omnilidar.domains import ground as G
from omnilidar.errors import InputError
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import PRESETS

EFFECTS = [("fog", "heavy"), ("snow", "light"), ("rain", "heavy"), ("wet_ground", "heavy"),
           ("beam_reduction", "half"), ("beam_missing", "light")]


def _bad(scan: Scan, problem: str) -> Scan:
    pts = scan.points[::40].copy()
    if problem == "nan":
        pts[5, 1] = np.nan
    elif problem == "0..255":
        pts[:, 3] = np.linspace(0.0, 255.0, len(pts), dtype=np.float32)
    extra = [None if a is None else np.asarray(a)[::40] for a in (scan.semantic, scan.instance, scan.ring)]
    return Scan(pts, *extra, scan.boxes, scan.intensity_scale)


@pytest.mark.parametrize("name,severity", EFFECTS)
@pytest.mark.parametrize("problem", ["nan", "0..255"])
def test_apply_refuses_bad_points_before_any_work(name, severity, problem, synthetic_sweep, monkeypatch):
    monkeypatch.setattr(G, "estimate_ground", lambda *a, **k: pytest.fail("checked before any work"))
    effect = importlib.import_module(f"omnilidar.domains.effects.{name}")
    sensor = PRESETS["kitti_hdl64e"]
    params = effect.draw_params(severity, np.random.default_rng(0))
    match = "NaN or infinite" if problem == "nan" else "outside the kitti_hdl64e scale 0..1"
    with pytest.raises(InputError, match=match) as err:
        effect.apply(_bad(synthetic_sweep, problem), params, sensor, np.random.default_rng(0))
    assert str(err.value).startswith(f"{name}: ") and "\n" not in str(err.value)
