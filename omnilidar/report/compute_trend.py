"""Straight lines against log10 of compute, and how far out an extrapolation may still be read.

The GDA budget study (gain against generator CPU-minutes) and the decomposition's strength curves
(where SDEdited scans stop paying against generator iterations) both fit one; an extrapolation
beyond ``FAR_DECADES`` is reported as out of reach rather than as a many-digit budget.
"""

from __future__ import annotations

import numpy as np

FAR_DECADES = 12  # beyond 1e12 iterations no budget anyone could spend reaches it


def fit_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float | None]:
    """Least-squares slope, intercept and the slope's standard error (None with two points or fewer)."""
    if len(set(x.tolist())) < 2:
        return 0.0, float(y.mean()), None
    slope, intercept = np.polyfit(x, y, 1)
    if len(x) <= 2:
        return float(slope), float(intercept), None
    residual = y - (intercept + slope * x)
    spread = np.sum((x - x.mean()) ** 2)
    return float(slope), float(intercept), float(np.sqrt(np.sum(residual ** 2) / (len(x) - 2) / spread))
