"""What running more single-threaded CPU jobs than cores costs: Voxel R-CNN training steps.

    python benchmarks/bench_concurrency.py [--steps 20] [--points 12000]

Starts k worker processes at once (torch with one thread each, like the workflow's jobs),
each running the same CPU_SMALL Voxel R-CNN training step on the synthetic KITTI-grid
scene of bench_det_voxelrcnn.py, for k = the machine's cores and k = twice that (what
`snakemake -j4` starts on a 2-core machine without a cap). Prints the median step time
per worker and the aggregate throughput (steps per second over all workers) of each k,
and their ratio. Because of this ratio the workflow's resources.smk gives a local run at most
the machine's cores (resources.one_job_per_core).
"""

from __future__ import annotations

import argparse
import copy
import json
import multiprocessing as mp
import os
import statistics
import sys
import time
from pathlib import Path

import torch
import yaml

sys.path.insert(0, str(Path(__file__).parent))
import bench_record  # noqa: E402
from bench_det_voxelrcnn import RANGE, VOXEL, synthetic_batch  # noqa: E402

from omnilidar.dicts import deep_merge  # noqa: E402
from omnilidar.downstream.det.models.detector import build_detector  # noqa: E402


def worker(rank: int, steps: int, points: int, barrier, results) -> None:
    torch.set_num_threads(1)
    doc = yaml.safe_load((Path(__file__).parent.parent / "config" / "detectors" / "voxel_rcnn.yaml").read_text())
    torch.manual_seed(rank)
    model = build_detector(copy.deepcopy(deep_merge(doc["MODEL"], doc["CPU_SMALL"])), 1, ["Car"], RANGE, VOXEL)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    batch = synthetic_batch(points, 2, seed=rank)
    model.train()
    for _ in range(2):  # warm-up before the common start
        ret, _, _ = model(dict(batch))
        opt.zero_grad()
        ret["loss"].backward()
        opt.step()
    barrier.wait()
    times = []
    for _ in range(steps):
        t = time.perf_counter()
        ret, _, _ = model(dict(batch))
        opt.zero_grad()
        ret["loss"].backward()
        opt.step()
        times.append(time.perf_counter() - t)
    results.put((rank, times))


def run(k: int, steps: int, points: int) -> dict:
    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(k + 1), ctx.Queue()
    procs = [ctx.Process(target=worker, args=(r, steps, points, barrier, results)) for r in range(k)]
    for p in procs:
        p.start()
    barrier.wait()
    start = time.perf_counter()
    per_worker = [results.get() for _ in procs]
    wall = time.perf_counter() - start
    for p in procs:
        p.join()
    medians = [statistics.median(t) for _, t in per_worker]
    return {"workers": k, "median_step_s": [round(m, 3) for m in medians], "wall_s": round(wall, 2),
            "steps_per_s": round(k * steps / wall, 3)}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--points", type=int, default=12000)
    bench_record.out_arg(parser)
    args = parser.parse_args()
    cores = len(os.sched_getaffinity(0))
    one_per_core = run(cores, args.steps, args.points)
    oversubscribed = run(2 * cores, args.steps, args.points)
    figures = {"cores": cores, "one_per_core": one_per_core, "two_per_core": oversubscribed,
               "throughput_ratio_two_vs_one_per_core": round(oversubscribed["steps_per_s"] / one_per_core["steps_per_s"], 3)}
    print(json.dumps(figures, indent=1))
    steps = [statistics.median(r["median_step_s"]) for r in (one_per_core, oversubscribed)]
    bench_record.write(args.out, [{
        "what": f"{2 * cores} vs {cores} single-thread Voxel R-CNN (CPU_SMALL) training processes on the {cores} cores: "
                "aggregate steps per second (why local runs start one job per core)",
        "median": f"{2 * cores} processes get {figures['throughput_ratio_two_vs_one_per_core']:.3g}x the steps per second "
                  f"of {cores} (median step {steps[0]:.2f} s with {cores}, {steps[1]:.2f} s with {2 * cores})"}], figures)


if __name__ == "__main__":
    main()
