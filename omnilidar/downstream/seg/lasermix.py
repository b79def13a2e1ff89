"""LaserMix (Kong et al., CVPR 2023): mixing two scans along laser-inclination partitions.

The inclination range covered by both scans is cut into ``areas`` equal bands;
bands of one parity come from scan A, the others from scan B, each point keeping
its own label. Semi-supervised methods mix a labelled scan with an unlabelled one
(supervised by a teacher's labels); the decomposition study mixes a real labelled
scan with a real unlabelled one whose labels come from the fixed labeler, so that
it can be set against GDA, which spends the same labeler on generated scans.
"""

from __future__ import annotations

import numpy as np

AREAS = (2, 3, 4, 5, 6)  # LaserMix draws the number of bands from these


def inclination(points: np.ndarray) -> np.ndarray:
    """Elevation angle (rad) of each point seen from the sensor origin."""
    return np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))


def laser_mix(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray],
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One mixed scan (points, labels) of scans ``a`` and ``b`` (each (points, labels)).

    The number of bands comes from :data:`AREAS` and which scan gives the even
    bands from ``rng``; both are part of the draw, so a mix is reproducible.
    """
    areas = int(rng.choice(AREAS))
    parity = int(rng.integers(2))
    pitch_a, pitch_b = inclination(a[0]), inclination(b[0])
    both = np.concatenate([pitch_a, pitch_b])
    if both.size == 0:
        return a
    lo, hi = float(both.min()), float(both.max())
    width = max(hi - lo, 1e-9) / areas

    def band(pitch: np.ndarray) -> np.ndarray:
        return np.clip(((pitch - lo) / width).astype(np.int64), 0, areas - 1)

    keep_a = (band(pitch_a) + parity) % 2 == 0
    keep_b = (band(pitch_b) + parity) % 2 == 1
    points = np.concatenate([a[0][keep_a], b[0][keep_b]])
    labels = np.concatenate([a[1][keep_a], b[1][keep_b]])
    return points, labels
