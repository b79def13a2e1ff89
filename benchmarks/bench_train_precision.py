"""Generator training in fp32 against bf16 autocast, as the workflow runs it, on this CPU.

    python benchmarks/bench_train_precision.py --run-dir /path/to/quick-start-clone --iterations 40 \
        --out docs/results/bench_train_precision.json

Takes the ``train-generator`` command a quick-start clone ran (its logs/generator/train_full.log)
and runs it twice at the same time for ``--iterations`` iterations: once with training.bf16 true,
once false, each in its own work folder and on one thread. Started together, both runs see the
same machine, whose speed varies from one minute to the next; on a machine with two or more
cores each run is pinned to its own core, and ``--repeats`` swaps the cores and which run starts
first. Prints each run's wall time and the bf16 / fp32 ratio. bf16 applies only on a CPU with native
bf16 (AVX512-BF16 or AMX); the bf16 run's log says whether it did.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import bench_record


def command(run_dir: Path, iterations: int, bf16: bool, work: Path) -> list[str]:
    """The clone's train-generator command, cut to ``iterations`` and set to ``bf16``, writing under ``work``."""
    first = (run_dir / "logs" / "generator" / "train_full.log").read_text().splitlines()[0]
    if not first.startswith("$ omnilidar train-generator"):
        raise SystemExit(f"{run_dir}/logs/generator/train_full.log does not start with the train-generator command")
    argv = shlex.split(first[2:])
    at = argv.index("--settings") + 1
    settings = json.loads(argv[at])
    settings["training"].update(iterations=iterations, checkpoint_interval=10 * iterations, bf16=bf16)
    argv[at] = json.dumps(settings)
    for flag, value in (("--work-dir", work / "state"), ("--out", work / "model.pt"), ("--threads", "1")):
        argv[argv.index(flag) + 1] = str(value)
    return argv


def race(run_dir: Path, iterations: int, first: str, tmp: Path) -> dict[str, dict]:
    """Both precisions at once (``first`` started a second earlier, on the first core): wall seconds
    and whether bf16 applied."""
    procs = {}
    cores = sorted(os.sched_getaffinity(0))
    for slot, precision in enumerate((first, "fp32" if first == "bf16" else "bf16")):
        work = tmp / f"{precision}_{len(list(tmp.iterdir()))}"
        work.mkdir(parents=True)
        log = open(work / "log", "w")
        core = {cores[slot % len(cores)]}
        procs[precision] = (subprocess.Popen(command(run_dir, iterations, precision == "bf16", work), cwd=run_dir,
                                             stdout=log, stderr=subprocess.STDOUT,
                                             preexec_fn=lambda core=core: os.sched_setaffinity(0, core)),
                            time.perf_counter(), work, log)
        time.sleep(1)
    out = {}
    for precision, (proc, start, work, log) in procs.items():
        if proc.wait():
            raise SystemExit(f"{precision} run failed; see {work / 'log'}")
        log.close()
        out[precision] = {"wall_s": time.perf_counter() - start,
                          "bf16_applied": "bf16 autocast on the CPU" in (work / "log").read_text()}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run-dir", type=Path, required=True, help="a clone that ran the quick start")
    ap.add_argument("--iterations", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=2, help="races, alternating which run starts first")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    races = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            result = race(args.run_dir, args.iterations, ("bf16", "fp32", "fp32", "bf16")[r % 4], Path(tmp))
            races.append(result)
            print(f"race {r + 1}: bf16 {result['bf16']['wall_s']:.1f} s (applied: {result['bf16']['bf16_applied']}), "
                  f"fp32 {result['fp32']['wall_s']:.1f} s, ratio {result['bf16']['wall_s'] / result['fp32']['wall_s']:.2f}",
                  flush=True)
    if not all(r["bf16"]["bf16_applied"] for r in races):
        print("this CPU has no native bf16: both runs trained in fp32", file=sys.stderr)
    fp32 = statistics.median(r["fp32"]["wall_s"] for r in races)
    bf16 = statistics.median(r["bf16"]["wall_s"] for r in races)
    what = f"generator training, {args.iterations} iterations of the quick start's settings, one thread, both runs at once"
    rows = [{"what": f"{what}: fp32", "median": f"{fp32:.1f} s"},
            {"what": f"{what}: bf16 autocast", "median": f"{bf16:.1f} s ({bf16 / fp32:.2f}x fp32)"}]
    bench_record.write(args.out, rows, {"races": races, "iterations": args.iterations})


if __name__ == "__main__":
    main()
