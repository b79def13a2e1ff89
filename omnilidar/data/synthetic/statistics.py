"""Summary statistics of a set of scans, for comparing synthetic and real data.

Everything returned is plain JSON (floats, ints, lists, dicts) so that a workflow
target can store it as is.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from omnilidar.lidar.scan import Scan

RANGE_EDGES = (0.0, 5.0, 10.0, 20.0, 30.0, 50.0, 80.0, 120.0)
ELEVATION_EDGES_DEG = tuple(float(e) for e in np.arange(-26.0, 5.0, 1.0))


def _class_names() -> dict[int, str]:
    from omnilidar.io.semantickitti import CLASS_NAMES, LEARNING_MAP

    return {raw: ("unlabeled" if train == 0 else CLASS_NAMES[train - 1]) for raw, train in LEARNING_MAP.items()}


def scan_statistics(scans: Iterable[Scan]) -> dict:
    """Statistics over ``scans``.

    Keys: ``num_scans``; ``points_per_scan`` (mean, median, min, max);
    ``range_edges_m`` and ``range_fraction`` (share of points per range bin);
    ``zero_remission_fraction`` overall and ``zero_remission_by_range`` per
    range bin; ``mean_remission_by_range`` (0..1 scale); ``elevation_edges_deg``
    and ``elevation_fraction`` (share of points per 1-degree elevation bin);
    ``points_per_ring`` (mean points per ring per scan, the row occupancy
    profile; ``None`` when scans carry no rings);
    ``class_fraction`` (share of labelled points per SemanticKITTI learning
    class name, when labels exist: ``None`` otherwise).
    """
    names = _class_names()
    counts, r_hist, z_hist, i_sum, e_hist = [], np.zeros(len(RANGE_EDGES) - 1), np.zeros(len(RANGE_EDGES) - 1), \
        np.zeros(len(RANGE_EDGES) - 1), np.zeros(len(ELEVATION_EDGES_DEG) - 1)
    class_counts: dict[str, int] = {}
    labelled = 0
    ring_acc = np.zeros(0)
    for scan in scans:
        n = len(scan)
        counts.append(n)
        if n == 0:
            continue
        xyz = scan.xyz.astype(np.float64)
        r = np.linalg.norm(xyz, axis=1)
        inten = scan.intensity.astype(np.float64) / float(scan.intensity_scale)
        rb = np.clip(np.digitize(r, RANGE_EDGES) - 1, 0, len(RANGE_EDGES) - 2)
        r_hist += np.bincount(rb, minlength=len(r_hist))
        z_hist += np.bincount(rb, weights=(inten == 0).astype(np.float64), minlength=len(r_hist))
        i_sum += np.bincount(rb, weights=inten, minlength=len(r_hist))
        elev = np.degrees(np.arcsin(np.clip(xyz[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0)))
        e_hist += np.histogram(elev, bins=ELEVATION_EDGES_DEG)[0]
        if scan.semantic is not None:
            raw, cnt = np.unique(scan.semantic, return_counts=True)
            for k, c in zip(raw.tolist(), cnt.tolist()):
                name = names.get(int(k), "unlabeled")
                class_counts[name] = class_counts.get(name, 0) + int(c)
            labelled += n
        if scan.ring is not None:
            rc = np.bincount(scan.ring.astype(np.int64))
            size = max(len(ring_acc), len(rc))
            ring_acc = np.pad(ring_acc, (0, size - len(ring_acc))) + np.pad(rc, (0, size - len(rc)))
    total = max(float(r_hist.sum()), 1.0)
    num = len(counts)

    def frac(a, b):
        return [float(x / y) if y > 0 else 0.0 for x, y in zip(a, b)]

    ring_profile = [float(c / num) for c in ring_acc] if len(ring_acc) and num else None
    return {
        "num_scans": num,
        "points_per_scan": {
            "mean": float(np.mean(counts)) if counts else 0.0,
            "median": float(np.median(counts)) if counts else 0.0,
            "min": int(np.min(counts)) if counts else 0,
            "max": int(np.max(counts)) if counts else 0,
        },
        "range_edges_m": list(RANGE_EDGES),
        "range_fraction": [float(x / total) for x in r_hist],
        "zero_remission_fraction": float(z_hist.sum() / total) if r_hist.sum() else 0.0,
        "zero_remission_by_range": frac(z_hist, r_hist),
        "mean_remission_by_range": frac(i_sum, r_hist),
        "elevation_edges_deg": list(ELEVATION_EDGES_DEG),
        "elevation_fraction": [float(x / total) for x in e_hist],
        "points_per_ring": ring_profile,
        "class_fraction": ({k: float(v / labelled) for k, v in sorted(class_counts.items())} if labelled else None),
    }
