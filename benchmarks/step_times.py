"""Training step times of a workflow run, read from its jobs' logs: how fast each trainer stepped
where the run happened (a GPU machine, a cluster node), as a result file for the docs.

    python benchmarks/step_times.py --run-dir /path/to/run --machine-gpu "NVIDIA H200" --machine-cpus 16 \
        --torch 2.11.0+cu130 --out docs/results/bench_step_times_gpu.json

Every trainer logs mmengine's ``Iter(train) [i/N] ... time: T`` (seconds per step, averaged over the
log interval) to its Snakemake log: the generator (logs/generator/), the labeler
(logs/downstream/labeler.log) and the students (logs/downstream/train/, MinkUNet and SPVCNN apart).
Prints and records, per trainer, the jobs, the steps logged, the median and range of the logged
step times, and the jobs whose loss went non-finite (with the last iteration each logged). Jobs that ran side by side share the machine: the times are the run's, not one job's alone.
"""

from __future__ import annotations

import argparse
import re
import statistics
from pathlib import Path

import bench_record

STEP = re.compile(r"Iter\(train\) \[\s*(\d+)/(\d+)\].*?\btime: ([0-9.]+)")
DIVERGED = "training diverged (non-finite loss)"  # the trainers' FloatingPointError
TRAINERS = {"generator": "generator/*.log", "labeler": "downstream/labeler.log",
            "MinkUNet student": "downstream/train/*minkunet*.log", "SPVCNN student": "downstream/train/*spvcnn*.log"}


def logged_steps(text: str) -> list[tuple[int, int, float]]:
    """(iteration, of iterations, seconds per step) of every logged training line."""
    return [(int(i), int(n), float(t)) for i, n, t in STEP.findall(text)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run-dir", type=Path, required=True, help="the working directory the run happened in")
    ap.add_argument("--machine-gpu", default=None, help="the GPU the run used, by name")
    ap.add_argument("--machine-cpus", type=int, required=True, help="the run machine's CPU cores")
    ap.add_argument("--torch", required=True, help="the run machine's torch version")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    rows, figures = [], {}
    for name, pattern in TRAINERS.items():
        texts = {log.name: log.read_text(errors="replace") for log in sorted((args.run_dir / "logs").glob(pattern))}
        steps = {log: logged_steps(text) for log, text in texts.items()}
        times = [t for s in steps.values() for _, _, t in s]
        if not times:
            continue
        reached = {log: s[-1][0] for log, s in steps.items() if s}
        diverged = {log: reached.get(log, 0) for log, text in texts.items() if DIVERGED in text}
        figures[name] = {"jobs": len(steps), "median_s": statistics.median(times), "min_s": min(times),
                         "max_s": max(times), "last_iteration": reached, "diverged": diverged}
        note = (f"; {len(diverged)} diverged (non-finite loss) after iteration {min(diverged.values())}-"
                f"{max(diverged.values())}" if diverged else "")
        line = (f"{name}: {len(steps)} job(s), {len(times)} logged intervals, step median {statistics.median(times):.2f} s "
                f"(range {min(times):.2f}-{max(times):.2f} s){note}")
        print(line)
        rows.append({"what": f"{name} training step ({len(steps)} job(s), {len(times)} logged intervals{note})",
                     "median": f"{statistics.median(times):.2f} s (range {min(times):.2f}-{max(times):.2f} s)"})
    if not rows:
        raise SystemExit(f"{args.run_dir}: no training log lines under logs/")
    machine = {"cpus": args.machine_cpus, "processor": "x86_64", "torch": args.torch}
    if args.machine_gpu:
        machine["gpu"] = args.machine_gpu
    bench_record.write(args.out, rows, figures, machine=machine)


if __name__ == "__main__":
    main()
