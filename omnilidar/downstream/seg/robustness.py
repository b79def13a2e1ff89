"""Robustness scores on corrupted sets (Robo3D's mCE and mRR).

For corruption i at severities l = 1..L (mIoU as fractions):

    CE_i = sum_l (1 - mIoU_il) / sum_l (1 - mIoU_il^baseline)      mCE = mean_i CE_i
    RR_i = sum_l mIoU_il / (L * mIoU_clean)                          mRR = mean_i RR_i

reported in percent. The paper normalises CE by its own supervised-only model
(which therefore scores 100); Robo3D normalises by MinkUNet18 (cr 1.0), whose
SemanticKITTI-C table gives one mIoU per corruption (the mean over severities),
so its baseline sum is L times that value.
"""

from __future__ import annotations

import numpy as np

# Robo3D SemanticKITTI-C, MinkUNet18 (cr 1.0) mIoU in percent (REFERENCE section 7).
ROBO3D_MINKUNET18 = {
    "clean": 62.76, "fog": 55.87, "wet_ground": 53.99, "snow": 53.28, "motion_blur": 32.92,
    "beam_missing": 56.32, "crosstalk": 58.34, "incomplete_echo": 54.43, "cross_sensor": 46.05,
}


def corruption_error(miou: list[float], baseline: list[float]) -> float:
    """CE in percent from per-severity mIoUs (fractions) of a model and its baseline."""
    denom = float(np.sum(1.0 - np.asarray(baseline, np.float64)))
    if denom <= 0:
        return float("nan")
    return 100.0 * float(np.sum(1.0 - np.asarray(miou, np.float64))) / denom


def resilience_rate(miou: list[float], clean: float) -> float:
    """RR in percent: mean corrupted mIoU over the clean mIoU."""
    if clean <= 0:
        return float("nan")
    return 100.0 * float(np.mean(np.asarray(miou, np.float64))) / clean


def robustness(sets: dict[str, dict[str, float]], clean: float,
               baseline_sets: dict[str, dict[str, float]] | None = None,
               baseline_table: dict[str, float] | None = None) -> dict:
    """CE / RR per corruption and mCE / mRR.

    ``sets``: corruption -> severity -> mIoU (fraction). Exactly one of
    ``baseline_sets`` (same shape: our supervised-only model) or
    ``baseline_table`` (corruption -> mIoU in percent, e.g. :data:`ROBO3D_MINKUNET18`)
    gives the CE normaliser. NaN (undefined) scores are returned as None.
    """
    ce, rr = {}, {}
    for name, by_sev in sets.items():
        sev = sorted(by_sev)
        values = [by_sev[s] for s in sev]
        if baseline_sets is not None:
            base = [baseline_sets[name][s] for s in sev]
        else:
            base = [baseline_table[name] / 100.0] * len(sev)
        ce[name] = corruption_error(values, base)
        rr[name] = resilience_rate(values, clean)

    def mean(d):
        v = [x for x in d.values() if np.isfinite(x)]
        return float(np.mean(v)) if v else None

    def clean_nan(d):
        return {k: (float(v) if np.isfinite(v) else None) for k, v in d.items()}

    return {"ce": clean_nan(ce), "rr": clean_nan(rr), "mce": mean(ce), "mrr": mean(rr)}
