"""Return detection and remission of the synthetic LiDAR.

Physics kept deliberately simple and calibrated on real KITTI HDL-64E sweeps:

* received signal ~ reflectivity x (0.5 + 0.5 cos(incidence)) / range^2 with a
  log-normal speckle term. A return is DETECTED when that signal clears the
  detection threshold (``detection_range_m`` is the range at which a white
  Lambertian target at normal incidence sits exactly at threshold); dark,
  grazing and far surfaces drop out first. On top, a small fraction of returns
  is lost at random (``dropout_probability``) and grazing hits lose more
  (``grazing_dropout``).
* reported remission = reflectivity x (0.5 + 0.5 cos) x gain(range) x speckle,
  where gain is flat up to ``remission_knee_m`` and falls linearly beyond it
  (KITTI's remission is range-compensated near the car and not far away),
  clipped to [0, 0.99] and quantised to two decimals as KITTI stores it.
* KITTI reports EXACTLY ZERO remission for weak returns (a bimodal pattern:
  ~8-10 % zeros but almost no values in (0, 0.05)). We model that with a second
  threshold, ``weak_return_range_m``: a return whose signal is below it reads 0,
  which is rare near the car and the rule beyond ~50 m; a small floor of random
  zeros (``zero_floor_probability``) reproduces the zeros seen at short range.
"""

from __future__ import annotations

import numpy as np


def effective_reflectance(reflectivity: np.ndarray, cos_incidence: np.ndarray) -> np.ndarray:
    """Response between Lambertian and retro-reflective: half the signal survives at grazing incidence."""
    return reflectivity * (0.5 + 0.5 * np.clip(cos_incidence, 0.0, 1.0))


def detect(reflectivity: np.ndarray, cos_incidence: np.ndarray, rng_range: np.ndarray, settings: dict,
           rng: np.random.Generator) -> np.ndarray:
    """Boolean mask of returns the sensor reports (before its range limits)."""
    n = len(rng_range)
    speckle = np.exp(rng.normal(0.0, float(settings["speckle_sigma"]), n))
    signal = effective_reflectance(reflectivity, cos_incidence) * speckle * (
        float(settings["detection_range_m"]) / np.maximum(rng_range, 1e-3)) ** 2
    keep = signal >= 1.0
    u = rng.uniform(0.0, 1.0, n)
    grazing = np.clip(1.0 - np.clip(cos_incidence, 0.0, 1.0) / 0.2, 0.0, 1.0)  # 1 at 90 deg, 0 below ~78 deg
    p_drop = float(settings["dropout_probability"]) + float(settings["grazing_dropout"]) * grazing
    return keep & (u >= p_drop)


def remission(reflectivity: np.ndarray, cos_incidence: np.ndarray, rng_range: np.ndarray, settings: dict,
              rng: np.random.Generator, quantum: float = 0.01, top: float = 0.99) -> np.ndarray:
    """Remission in [0, top] (0..1 scale), quantised to multiples of ``quantum``
    (KITTI: 0.01 and 0.99), with KITTI's exact zeros (float64)."""
    n = len(rng_range)
    sigma = float(settings["speckle_sigma"])
    rho = effective_reflectance(reflectivity, cos_incidence)
    knee = float(settings["remission_knee_m"])
    slope = float(settings["remission_falloff_per_10m"]) / 10.0
    gain = np.clip(1.0 - slope * np.maximum(rng_range - knee, 0.0), 0.2, 1.0)
    value = rho * gain * np.exp(rng.normal(0.0, 0.5 * sigma, n))
    weak = rho * np.exp(rng.normal(0.0, sigma, n)) * (
        float(settings["weak_return_range_m"]) / np.maximum(rng_range, 1e-3)) ** 2 < 1.0
    weak |= rng.uniform(0.0, 1.0, n) < float(settings["zero_floor_probability"])
    value = np.where(weak, 0.0, value)
    return np.round(np.clip(value, 0.0, top) / quantum) * quantum
