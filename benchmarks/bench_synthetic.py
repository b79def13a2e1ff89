"""Speed of the synthetic world on ONE core.

    python benchmarks/bench_synthetic.py [--repeats 5] [--full]

Prints the first-call time of the numba kernels (loading them from numba's disk
cache, or compiling them when the cache is cold) separately from steady-state
medians: scene generation, and one sweep per sensor preset (ray casting +
radiometry + labels). Target: a 64 x 2083 KITTI sweep in <= 0.5 s. ``--full``
also generates every default shard (the embedded default) into a temporary
folder and reports the total CPU time (target: about 2 minutes).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import bench_record  # noqa: E402


def median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--full", action="store_true", help="also generate the whole default dataset")
    bench_record.out_arg(parser)
    args = parser.parse_args()

    t0 = time.perf_counter()
    from omnilidar.config import section_defaults
    from omnilidar.data.synthetic import raycast
    from omnilidar.data.synthetic.render import render_scan
    from omnilidar.data.synthetic.scene import generate_scene
    from omnilidar.data.synthetic.trajectory import route_poses
    from omnilidar.lidar.sensors import PRESETS

    print(f"import (numba + package): {time.perf_counter() - t0:.2f} s")
    settings = section_defaults("synthetic")
    rng = np.random.default_rng(0)
    scene = generate_scene(rng, settings["world"], 57.0)
    spec = PRESETS["kitti_hdl64e"]
    pose = route_poses(scene, "vehicle", spec, 1, 1.0, rng)[0]
    start = time.perf_counter()
    render_scan(scene, spec, pose, np.random.default_rng(1), settings["radiometry"])
    print(f"first sweep (numba cache load or compile + one sweep): {time.perf_counter() - start:.2f} s")

    gen = median_time(lambda: generate_scene(np.random.default_rng(5), settings["world"], 57.0), args.repeats)
    print(f"scene generation (57 m route, {len(scene.prims)} primitives): median {gen:.3f} s")
    print(f"{'sensor':<16}{'rays':>9}{'points':>9}{'cast s':>9}{'sweep s':>9}{'target':>9}")
    kitti_sweep, sweeps = None, {}
    for name, platform in (("kitti_hdl64e", "vehicle"), ("nuscenes_hdl32e", "vehicle"), ("drone_os64", "drone"),
                           ("quadruped_os64", "quadruped")):
        spec = PRESETS[name]
        pose = route_poses(scene, platform, spec, 1, 1.0, np.random.default_rng(2))[0]
        rot = pose.rotation(spec.mount_pitch_deg)
        origin = np.asarray(pose.position)
        cast = median_time(lambda: raycast.cast(scene.ground, scene.prims, origin, rot, spec.elevations_rad,
                                                spec.azimuths_rad, spec.max_range), args.repeats)
        scan = render_scan(scene, spec, pose, np.random.default_rng(3), settings["radiometry"])
        sweep = median_time(lambda: render_scan(scene, spec, pose, np.random.default_rng(3), settings["radiometry"]),
                            args.repeats)
        target = "<= 0.5" if name == "kitti_hdl64e" else ""
        if name == "kitti_hdl64e":
            kitti_sweep, kitti_cast, kitti_rays = sweep, cast, spec.num_beams * spec.azimuth_steps
        sweeps[name] = {"rays": spec.num_beams * spec.azimuth_steps, "points": len(scan), "cast_s": cast, "sweep_s": sweep}
        print(f"{name:<16}{spec.num_beams * spec.azimuth_steps:>9}{len(scan):>9}{cast:>9.3f}{sweep:>9.3f}{target:>9}")
    print(f"KITTI sweep / 0.5 s target: {kitti_sweep / 0.5:.2f}")
    bench_record.write(args.out, [
        {"what": f"synthetic KITTI sweep ({PRESETS['kitti_hdl64e'].num_beams} x {kitti_rays // PRESETS['kitti_hdl64e'].num_beams} rays)",
         "median": f"{kitti_sweep:.3f} s (ray cast {kitti_cast:.3f} s)", "target": "<= 0.5 s"},
        {"what": "synthetic scene generation", "median": f"{gen:.2f} s per scene"},
    ], {"scene_generation_s": gen, "sweeps": sweeps})

    if args.full:
        from omnilidar.data.synthetic.export import DATASETS, shard_names, write_shard

        cpu0, wall0 = time.process_time(), time.perf_counter()
        scans = 0
        with tempfile.TemporaryDirectory() as tmp:
            for dataset in DATASETS:
                for shard in shard_names(dataset, settings):
                    summary = write_shard(dataset, shard, settings, 0, Path(tmp) / dataset / shard)
                    scans += summary["scans"]
        print(f"whole embedded default: {scans} scans, CPU {time.process_time() - cpu0:.1f} s, "
              f"wall {time.perf_counter() - wall0:.1f} s (target ~120 s CPU)")


if __name__ == "__main__":
    main()
