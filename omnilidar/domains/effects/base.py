"""The contract every effect module follows, and the labels of added points.

An effect module ``omnilidar.domains.effects.<name>`` defines:

``NEEDS_GROUND: bool``
    Whether ``apply`` needs a ground mask (the builder estimates ground only then).
``SEVERITIES: dict[str, dict]``
    Named presets ("light", "moderate", "heavy") -> the severity parameters.
``draw_params(severity: str, rng) -> dict``
    Draw the concrete, JSON-serialisable parameters of one scan (e.g. fog's
    attenuation drawn per scan). Stored in the domain sidecar, so that
    ``apply(scan, params, ...)`` regenerates the scan exactly.
``DEFAULT_FIDELITY: dict`` and ``FIDELITY_LEVELS: dict[str, list]``
    Numerical knobs (samples per beam, integral resolution, ...) with the chosen
    defaults and the candidate values for the accuracy/time study.
``is_identity(params) -> bool`` (optional)
    True when ``apply`` with these parameters returns its input (e.g. zero water):
    the builder then skips the step and computes nothing for it (no ground).
``apply(scan, params, sensor, rng, *, ground=None, fidelity=None) -> Scan``
    A pure function: returns a new Scan, never mutates its input. Kept points stay
    in input order; labels, instance ids and rings follow their points; boxes are
    carried along. Zero severity returns the input bit for bit. Works in physical
    units internally (reflectance 0..1 = intensity / sensor.intensity_scale) and
    returns intensities in the sensor's scale and range.
"""

from __future__ import annotations

import numpy as np

# Raw SemanticKITTI id given to returns an effect creates (fog/snow/rain scatter
# returns): 1 = "outlier", which the official learning map sends to ignore (0).
# Such points are neither counted as right nor wrong in mIoU, as in SemanticKITTI-C.
WEATHER_RETURN_LABEL = 1

SEVERITY_NAMES = ("light", "moderate", "heavy")


def unchanged(scan, return_info: bool):
    """What ``apply`` returns when the effect does nothing: the input itself (bit for
    bit), with all-false info masks when ``return_info`` is asked for."""
    if not return_info:
        return scan
    n = len(scan)
    return scan, {"lost": np.zeros(n, bool), "changed": np.zeros(n, bool), "weather": np.zeros(n, bool)}
