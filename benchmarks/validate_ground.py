"""Validate omnilidar.domains.ground.estimate_ground on every platform. Run:

    python benchmarks/validate_ground.py [--scenes 4] [--figure-dir /tmp] [--out docs/results/bench_ground.json]

1. Ray-cast test scenes (tests/ground_scenes.py: sloped ground plane, 0.15 m
   curbs, cars, walls, poles, pedestrians) seen from the vehicle (HDL-64E at
   1.73 m), drone (OS1-64 at 10 m, pitched 20 deg down) and quadruped (OS1-64
   at 0.65 m) presets, flat and sloped, also with a 3 deg pitch error and a
   mount height off by 2x: precision / recall / IoU against the labels, and time.
2. Real KITTI scans (no labels): fraction of points called ground, fraction of
   those within +-0.2 m of a plane fitted to them within 20 m, the plane's
   height at the sensor (expected about -1.73 m), and a BEV figure per scan.
3. The 50-point labelled SemanticKITTI pair (tiny, indicative only).
4. The synthetic world (omnilidar.data.synthetic), when its settings schema is
   in place: a few rendered scans per platform against their labels.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import bench_record  # noqa: E402  (benchmarks/, the script's folder)
from ground_scenes import make_scene, platform_sensors, tilted  # noqa: E402
from real_samples import KITTI_SCANS, SEMANTICKITTI_SCAN, SEMANTICKITTI_TINY, real_files_or_exit  # noqa: E402

from omnilidar.domains.ground import estimate_ground, ground_truth_mask, mask_scores  # noqa: E402
from omnilidar.lidar.scan import Scan  # noqa: E402
from omnilidar.lidar.sensors import PRESETS  # noqa: E402



def synthetic_table(n_scenes: int) -> None:
    print("synthetic ray-cast scenes: mean (min) over scenes")
    print(f"{'platform':>10} {'case':>16} {'points':>7} {'gnd %':>6} {'precision':>15} {'recall':>15} "
          f"{'IoU':>15} {'ms':>6}")
    for platform, sensor in platform_sensors().items():
        cases = {
            "flat": (sensor, (0.0, 0.0)),
            "slope 4/-2 deg": (sensor, (4.0, -2.0)),
            "pitch err +3": (tilted(sensor, 3.0), (0.0, 0.0)),
            "height x2": (replace(sensor, mount_height=2 * sensor.mount_height), (0.0, 0.0)),
        }
        for case, (assumed, slope) in cases.items():
            rows = []
            for k in range(n_scenes):
                scan = make_scene(sensor, np.random.default_rng(100 + k), slope_deg=slope)
                truth = ground_truth_mask(scan.semantic)
                t0 = time.perf_counter()
                mask = estimate_ground(scan, assumed)
                dt = time.perf_counter() - t0
                rows.append({**mask_scores(mask, truth), "ms": dt * 1e3, "n": len(scan), "g": truth.mean()})
            agg = lambda key: f"{np.mean([r[key] for r in rows]):.3f} ({np.min([r[key] for r in rows]):.3f})"  # noqa: E731
            print(f"{platform:>10} {case:>16} {int(np.mean([r['n'] for r in rows])):>7} "
                  f"{100 * np.mean([r['g'] for r in rows]):6.1f} {agg('precision'):>15} {agg('recall'):>15} "
                  f"{agg('iou'):>15} {np.median([r['ms'] for r in rows]):6.1f}")


def real_table(figure_dir: Path | None) -> list[dict]:
    print("\nreal KITTI scans (HDL-64E preset; no labels)")
    results = []
    print(f"{'scan':>40} {'points':>7} {'ground %':>8} {'within 0.2 m':>12} {'plane z0':>8} {'ms':>6}")
    sensor = PRESETS["kitti_hdl64e"]
    for path in real_files_or_exit(KITTI_SCANS, SEMANTICKITTI_SCAN):
        pts = np.fromfile(path, np.float32).reshape(-1, 4)
        t0 = time.perf_counter()
        mask = estimate_ground(Scan(pts), sensor)
        dt = time.perf_counter() - t0
        g = pts[mask, :3].astype(np.float64)
        near = np.hypot(g[:, 0], g[:, 1]) < 20
        A = np.column_stack([g[near, 0], g[near, 1], np.ones(near.sum())])
        (a, b, c), *_ = np.linalg.lstsq(A, g[near, 2], rcond=None)
        within = np.abs(g[:, 2] - (a * g[:, 0] + b * g[:, 1] + c)) < 0.2
        name = "/".join(path.parts[-4:])
        print(f"{name:>40} {len(pts):>7} {100 * mask.mean():8.1f} {100 * within.mean():11.1f}% {c:8.3f} {dt * 1e3:6.1f}")
        results.append({"scan": name, "points": len(pts), "ground": float(mask.mean()),
                        "within_0.2m": float(within.mean()), "plane_z0": float(c), "ms": dt * 1e3})
        if figure_dir is not None:
            save_bev(pts, mask, figure_dir / f"ground_bev_{path.parts[-3]}_{path.stem}.png")
    return results


def save_bev(pts: np.ndarray, mask: np.ndarray, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(14, 7))
    for ax, lim in zip(axes, (40, 15)):
        ax.scatter(pts[~mask, 0], pts[~mask, 1], s=0.2, c="k", label="other")
        ax.scatter(pts[mask, 0], pts[mask, 1], s=0.2, c="g", label="ground")
        ax.set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal", xlabel="x (m)", ylabel="y (m)")
    axes[0].legend(markerscale=20, loc="upper right")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    print(f"{'':>40} figure: {out}")


def tiny_table() -> None:
    scan_path, label_path = real_files_or_exit(SEMANTICKITTI_TINY)
    pts = np.fromfile(scan_path, np.float32).reshape(-1, 4)
    sem = np.fromfile(label_path, np.uint32) & 0xFFFF
    scores = mask_scores(estimate_ground(Scan(pts), PRESETS["kitti_hdl64e"]), ground_truth_mask(sem))
    print(f"\nlabelled tiny pair ({len(pts)} points, indicative only): "
          + ", ".join(f"{k} {v:.3f}" for k, v in scores.items()))


def world_table(n_scans: int) -> dict[str, dict]:
    """Scans of the synthetic world per platform (skipped until it is complete)."""
    from omnilidar.errors import InputError

    try:
        from omnilidar.config import section_defaults
        from omnilidar.data.synthetic import render, scene, trajectory

        settings = section_defaults("synthetic")
        world, radiometry = settings["world"], settings["radiometry"]
    except (ImportError, InputError, KeyError) as err:
        print(f"\nsynthetic world: skipped ({err})")
        return {}
    print("\nsynthetic world (omnilidar.data.synthetic)")
    print(f"{'platform':>10} {'scans':>5} {'precision':>9} {'recall':>9} {'IoU':>9}")
    rng = np.random.default_rng(0)
    world_scene = scene.generate_scene(rng, world, 80.0)
    results = {}
    for platform, sensor in platform_sensors().items():
        poses = trajectory.route_poses(world_scene, platform, sensor, n_scans, 20.0, rng)
        scores = []
        for pose in poses:
            scan = render.render_scan(world_scene, sensor, pose, rng, radiometry)
            scores.append(mask_scores(estimate_ground(scan, sensor), ground_truth_mask(scan.semantic)))
        mean = {k: np.mean([s[k] for s in scores]) for k in scores[0]}
        print(f"{platform:>10} {len(scores):>5} {mean['precision']:9.3f} {mean['recall']:9.3f} {mean['iou']:9.3f}")
        results[platform] = {"scans": len(scores), **{k: float(v) for k, v in mean.items()}}
    return results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--figure-dir", type=Path, default=Path("/tmp"))
    bench_record.out_arg(ap)
    args = ap.parse_args()
    real_files_or_exit(KITTI_SCANS, SEMANTICKITTI_SCAN, SEMANTICKITTI_TINY)  # one line before any table
    synthetic_table(args.scenes)
    real = real_table(args.figure_dir)
    tiny_table()
    world = world_table(3)
    rows = [{"what": f"synthetic world, {platform} ({w['scans']} scans, labelled)",
             "result": f"precision {w['precision']:.3f}, recall {w['recall']:.3f}, IoU {w['iou']:.3f}"}
            for platform, w in world.items()]
    rows += [{"what": f"real KITTI {r['scan']} (no labels)",
              "result": f"{100 * r['ground']:.1f} % of points called ground, {100 * r['within_0.2m']:.1f} % of them "
                        f"within 0.2 m of a plane at {r['plane_z0']:.2f} m"} for r in real]
    bench_record.write(args.out, rows, {"synthetic_world": world, "real": real}, columns=["what", "result"])


if __name__ == "__main__":
    main()
