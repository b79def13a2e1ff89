"""Round-trip quality of the range-image projection on the real KITTI scans, and
ring-recovery agreement with the firing-order reference (KITTI) and the true rings
(nuScenes).

    python benchmarks/measure_projection_real.py [--table projection|rings] [--out FILE]

With --table one table only, so each can be its own result file (--out): docs/datasets.md is
written from docs/results/bench_projection_real.json and bench_rings_real.json. The ring table
also applies each KITTI scan's calibration (``calibrate_rings``) to the other scan's subsets.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

import bench_record  # benchmarks/, the script's folder
from omnilidar.data.range_image import RangeImageSpec, decode, encode, project
from omnilidar.data.rings import calibrate_rings, recover_rings
from omnilidar.lidar.sensors import PRESETS

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from real_samples import KITTI_SCANS, NUSCENES_SWEEP, real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)


PROJECTION_COLUMNS = ["scan", "image", "valid pixels", "points surviving", "median / max relative range error"]
RING_COLUMNS = ["scan", "subset", "nominal angles", "per-scan calibration", "calibrated on the other KITTI scan"]


def projection_table() -> list[dict]:
    kitti = real_files_or_exit(KITTI_SCANS)
    sensor = PRESETS["kitti_hdl64e"]
    print("Projection round trip, KITTI preset (+3/-25 deg, 1.45 < r < 80 m)")
    print(f"{'scan':<12}{'image':>10}{'valid px':>10}{'survive':>9}{'med rel err':>13}{'max rel err':>13}{'max abs err m':>15}")
    rows = []
    for path in kitti:
        pts = np.fromfile(path, np.float32).reshape(-1, 4)
        for width in (1024, 2048, 4096):
            spec = RangeImageSpec.from_sensor(sensor, width=width)
            proj = project(pts, spec)
            d, _, m = decode(encode(proj.range_img, proj.intensity_img, spec), spec)
            assert np.array_equal(m, proj.mask)
            truth = np.linalg.norm(pts[proj.point_index_img[m], :3].astype(np.float64), axis=1)
            err = np.abs(d[m].astype(np.float64) - truth)
            rel = err / truth
            print(
                f"{path.stem:<12}{f'64x{width}':>10}{proj.mask.mean():>10.4f}{proj.winner.sum() / len(pts):>9.4f}"
                f"{np.median(rel):>13.2e}{rel.max():>13.2e}{err.max():>15.2e}"
            )
            rows.append(dict(zip(PROJECTION_COLUMNS, (
                path.stem, f"64x{width}", f"{proj.mask.mean():.3f}", f"{proj.winner.sum() / len(pts):.3f}",
                f"{np.median(rel):.1e} / {rel.max():.1e}"))))
    return rows


def _firing_order_rings(points):
    turns = np.floor(np.unwrap(np.arctan2(points[:, 1], points[:, 0]).astype(np.float64)) / (2 * np.pi))
    return (turns - turns.min()).astype(np.int64)


def ring_table() -> list[dict]:
    print()
    print("Ring recovery agreement (fraction of points with the reference ring)")
    print(f"{'scan':<34}{'subset':<22}{'nominal':>9}{'calibrated':>12}{'other scan':>12}")
    sensor = PRESETS["kitti_hdl64e"]
    rng = np.random.default_rng(0)
    paths = real_files_or_exit(KITTI_SCANS)
    scans = [np.fromfile(path, np.float32).reshape(-1, 4) for path in paths]
    calibrations = [calibrate_rings(pts, sensor) for pts in scans]
    rows = []
    for k, (path, pts) in enumerate(zip(paths, scans)):
        ref = _firing_order_rings(pts)
        az = np.arctan2(pts[:, 1], pts[:, 0])
        perm = rng.permutation(len(pts))
        subsets = {
            "full": np.arange(len(pts)),
            "shuffled": perm,
            "front 90 deg crop": np.flatnonzero(np.abs(az) < np.pi / 4),
            "rear 180 deg crop": np.flatnonzero(np.abs(az) > np.pi / 2),
            "even rings only": np.flatnonzero(ref % 2 == 0),
        }
        other = calibrations[(k + 1) % len(scans)] if len(scans) > 1 else None
        for name, sel in subsets.items():
            nom = (recover_rings(pts[sel], sensor, calibrate=False) == ref[sel]).mean()
            cal = (recover_rings(pts[sel], sensor) == ref[sel]).mean()
            cross = (recover_rings(pts[sel], sensor, calibration=other) == ref[sel]).mean() if other else np.nan
            print(f"{'kitti ' + path.stem:<34}{name:<22}{nom:>9.4f}{cal:>12.4f}{cross:>12.4f}")
            rows.append(dict(zip(RING_COLUMNS, (f"KITTI {path.stem}", name, f"{nom:.4f}", f"{cal:.4f}",
                                                "" if other is None else f"{cross:.4f}"))))
    raw = np.fromfile(real_files_or_exit(NUSCENES_SWEEP)[0], np.float32).reshape(-1, 5)
    sensor = PRESETS["nuscenes_hdl32e"]
    truth = 31 - raw[:, 4].astype(np.int64)  # nuScenes counts rings bottom-up
    r = np.linalg.norm(raw[:, :3], axis=1)
    usable = (r > sensor.min_range) & (r < sensor.max_range)
    nom = recover_rings(raw[:, :4], sensor, calibrate=False) == truth
    cal = recover_rings(raw[:, :4], sensor) == truth
    for name, sel in (("all points", slice(None)), ("1 < r < 70 m", usable)):
        print(f"{'nuscenes (HDL-32E)':<34}{name:<22}{nom[sel].mean():>9.4f}{cal[sel].mean():>12.4f}")
        rows.append(dict(zip(RING_COLUMNS, ("nuScenes (HDL-32E, true rings)", name, f"{nom[sel].mean():.4f}",
                                            f"{cal[sel].mean():.4f}", ""))))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--table", choices=["projection", "rings"], default=None, help="one table only (default both)")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    if args.out is not None and args.table is None:
        ap.error("--out needs --table (one result file per table)")
    if args.table in (None, "projection"):
        rows = projection_table()
        if args.table:
            bench_record.write(args.out, rows, {}, columns=PROJECTION_COLUMNS)
    if args.table in (None, "rings"):
        rows = ring_table()
        if args.table:
            bench_record.write(args.out, rows, {}, columns=RING_COLUMNS)


if __name__ == "__main__":
    main()
