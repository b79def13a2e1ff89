"""What every Snakemake start costs (each cluster job re-parses the Snakefile): a dry run of
the headline target on the test configuration, with the parsed-module cache cold and warm.

    python benchmarks/bench_workflow_start.py [--repeats 5] [--against <git ref>]

With ``--against``, the same dry run on that commit's checkout (a ``git worktree``) is timed in
the same loop, alternating, so the ratio compares runs on one machine under one load.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DRY_RUN = ["-m", "snakemake", "-n", "--quiet", "rules", "--configfile", "config/test.yaml",
           "--", "results/semkitti_1pct.json"]


def dry_run_seconds(checkout: Path, cache: Path) -> float:
    env = dict(os.environ, PYTHONPATH=str(checkout), OMNILIDAR_CACHE_DIR=str(cache))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, *DRY_RUN], cwd=checkout, env=env, check=True, capture_output=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--against", help="a git ref to time beside the working tree")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        checkouts = {"working tree": ROOT}
        if args.against:
            other = tmp / "against"
            subprocess.run(["git", "worktree", "add", "--detach", str(other), args.against], cwd=ROOT,
                           check=True, capture_output=True)
            checkouts[args.against] = other
        times: dict[str, list[float]] = {f"{name}, {state}": [] for name in checkouts for state in ("cold", "warm")}
        try:
            for _ in range(args.repeats):
                for name, checkout in checkouts.items():
                    cache = tmp / "cache"
                    shutil.rmtree(cache, ignore_errors=True)
                    times[f"{name}, cold"].append(dry_run_seconds(checkout, cache))
                    times[f"{name}, warm"].append(dry_run_seconds(checkout, cache))
        finally:
            if args.against:
                subprocess.run(["git", "worktree", "remove", "--force", str(tmp / "against")], cwd=ROOT)
        medians = {k: statistics.median(v) for k, v in times.items()}
        base = medians["working tree, cold"]
        print(f"dry run of results/semkitti_1pct.json (config/test.yaml), median of {args.repeats}:")
        for key, value in medians.items():
            print(f"  {key:<40} {value:6.2f} s   {value / base:5.2f}x of the working tree's cold start")


if __name__ == "__main__":
    main()
