"""Domain fidelity on the real KITTI object and SemanticKITTI scans (issue 13, item 9).

    python benchmarks/measure_real_scan_fidelity.py [real-data root] [--out FILE]

Reference lasers: each file is stored in firing order (laser after laser, top
first, each one revolution from azimuth 0), so ``floor(unwrapped azimuth / 2 pi)``
counts lasers; the order is plausible on all three scans (64 revolutions, median
elevations strictly descending). For each scan and each way of finding rings:
which method ran and the fraction of points whose ring equals the reference.
"as stored" is what the domain builder sees; "shuffled" (seed 0) is the order-free
case; "unit calibration" labels the shuffled scan with ``calibrate_rings`` of the
stored one. Then Beam-32 (even rings): how many reference lasers the kept points
come from (32 means exact). Then wet ground: ground points lost at water heights
0, 1e-6, 1e-3, 0.2 (light), 1.0 (moderate) mm with noise floor 0.3, and 1.2 mm /
0.7 (heavy), on the estimated ground.
"""

from __future__ import annotations

import argparse
import os
import warnings
from pathlib import Path

import numpy as np

from omnilidar.data.rings import calibrate_rings, ring_recovery
from omnilidar.lidar.scan import Scan
from omnilidar.lidar.sensors import PRESETS
from omnilidar.domains import ground as G
from omnilidar.domains.effects import wet_ground as W

import bench_record  # benchmarks/, the script's folder

DEFAULT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
SCANS = ["kitti_object/velodyne/000000.bin", "kitti_object/velodyne/000001.bin",
         "semantickitti/sequences/00/velodyne/000000.bin"]
SENSOR = PRESETS["kitti_hdl64e"]
WATER = [(0.0, 0.3), (1e-6, 0.3), (1e-3, 0.3), (0.2, 0.3), (1.0, 0.3), (1.2, 0.7)]
COLUMNS = ["scan", "as stored", "shuffled", "shuffled, unit calibration", "nominal table",
           "Beam-32 keeps lasers", "wet ground: ground points lost at " + " / ".join(f"{h:g}" for h, _ in WATER) + " mm"]


def reference_lasers(points: np.ndarray) -> np.ndarray:
    turns = np.floor(np.unwrap(np.arctan2(points[:, 1], points[:, 0]).astype(np.float64)) / (2 * np.pi))
    return (turns - turns.min()).astype(np.int64)


def main(root: Path) -> list[dict]:
    warnings.simplefilter("ignore")  # the fallback warning is reported as method "nominal"
    rows = []
    for name in SCANS:
        pts = np.fromfile(root / name, np.float32).reshape(-1, 4)
        ref = reference_lasers(pts)
        perm = np.random.default_rng(0).permutation(len(pts))
        print(f"{name}: {len(pts)} points, {ref.max() + 1} reference lasers")
        found = {}
        rings, method = ring_recovery(pts, SENSOR)
        found["as stored"] = (method, np.mean(rings == ref))
        rings, method = ring_recovery(pts[perm], SENSOR)
        found["shuffled"] = (method, np.mean(rings == ref[perm]))
        cal = calibrate_rings(pts, SENSOR)
        if cal is not None:
            rings, method = ring_recovery(pts[perm], SENSOR, calibration=cal)
            found["shuffled, unit calibration"] = (method, np.mean(rings == ref[perm]))
        rings, method = ring_recovery(pts, SENSOR, calibrate=False)
        found["nominal table"] = (method, np.mean(rings == ref))
        for case, (method, agreement) in found.items():
            print(f"  {case:<28} {method:<17} agreement {agreement:.5f}")
        kept = ring_recovery(pts, SENSOR)[0] % 2 == 0
        lasers = len(np.unique(ref[kept]))
        print(f"  Beam-32 as stored: kept points come from {lasers} reference lasers")
        scan = Scan(pts)
        ground = G.estimate_ground(scan, SENSOR)
        lost = [int(W.apply(scan, {"water_height_mm": h, "noise_floor": nf}, SENSOR, np.random.default_rng(0),
                            ground=ground, return_info=True)[1]["lost"].sum()) for h, nf in WATER]
        print(f"  wet ground: {int(ground.sum())} ground points, lost at {[h for h, _ in WATER]} mm: {lost}")
        row = {"scan": name, "Beam-32 keeps lasers": f"{lasers} of {ref.max() + 1}",
               COLUMNS[-1]: f"{' / '.join(map(str, lost))} of {int(ground.sum())}"}
        row.update({case: f"{agreement:.4f} ({method})" for case, (method, agreement) in found.items()})
        rows.append(row)
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", nargs="?", type=Path, default=Path(os.environ.get("OMNILIDAR_REAL_DATA", DEFAULT)))
    bench_record.out_arg(ap)
    args = ap.parse_args()
    bench_record.write(args.out, main(args.root), {}, columns=COLUMNS)
