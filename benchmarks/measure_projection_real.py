"""Round-trip quality of the range-image projection on the real KITTI scans, and
ring-recovery agreement with the firing-order reference (KITTI) and the true rings
(nuScenes).

    python benchmarks/measure_projection_real.py
"""

import sys
from pathlib import Path

import numpy as np

from omnilidar.data.range_image import RangeImageSpec, decode, encode, project
from omnilidar.data.rings import recover_rings
from omnilidar.lidar.sensors import PRESETS

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from real_samples import KITTI_SCANS, NUSCENES_SWEEP, real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)


def projection_table():
    kitti = real_files_or_exit(KITTI_SCANS)
    sensor = PRESETS["kitti_hdl64e"]
    print("Projection round trip, KITTI preset (+3/-25 deg, 1.45 < r < 80 m)")
    print(f"{'scan':<12}{'image':>10}{'valid px':>10}{'survive':>9}{'med rel err':>13}{'max rel err':>13}{'max abs err m':>15}")
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


def _firing_order_rings(points):
    turns = np.floor(np.unwrap(np.arctan2(points[:, 1], points[:, 0]).astype(np.float64)) / (2 * np.pi))
    return (turns - turns.min()).astype(np.int64)


def ring_table():
    print()
    print("Ring recovery agreement (fraction of points with the reference ring)")
    print(f"{'scan':<34}{'subset':<22}{'nominal':>9}{'calibrated':>12}")
    sensor = PRESETS["kitti_hdl64e"]
    rng = np.random.default_rng(0)
    for path in real_files_or_exit(KITTI_SCANS):
        pts = np.fromfile(path, np.float32).reshape(-1, 4)
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
        for name, sel in subsets.items():
            nom = (recover_rings(pts[sel], sensor, calibrate=False) == ref[sel]).mean()
            cal = (recover_rings(pts[sel], sensor) == ref[sel]).mean()
            print(f"{'kitti ' + path.stem:<34}{name:<22}{nom:>9.4f}{cal:>12.4f}")
    raw = np.fromfile(real_files_or_exit(NUSCENES_SWEEP)[0], np.float32).reshape(-1, 5)
    sensor = PRESETS["nuscenes_hdl32e"]
    truth = 31 - raw[:, 4].astype(np.int64)  # nuScenes counts rings bottom-up
    r = np.linalg.norm(raw[:, :3], axis=1)
    usable = (r > sensor.min_range) & (r < sensor.max_range)
    nom = recover_rings(raw[:, :4], sensor, calibrate=False) == truth
    cal = recover_rings(raw[:, :4], sensor) == truth
    print(f"{'nuscenes (HDL-32E)':<34}{'all points':<22}{nom.mean():>9.4f}{cal.mean():>12.4f}")
    print(f"{'nuscenes (HDL-32E)':<34}{'1 < r < 70 m':<22}{nom[usable].mean():>9.4f}{cal[usable].mean():>12.4f}")


if __name__ == "__main__":
    projection_table()
    ring_table()
