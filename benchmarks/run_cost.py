"""What one workflow run cost: wall time, jobs and disk left behind, as a result file for the docs.

    python benchmarks/run_cost.py --run-dir /path/to/clone --target results/semkitti_1pct.json \
        --out docs/results/run_cost.json

Reads the run's Snakemake logs (``.snakemake/log/*.snakemake.log``): the first log that built
``--target`` gives the elapsed time from its first to its last timestamp and the jobs it finished.
With ``--after T`` the clone first built ``T`` in runs of its own and ``--target`` then built only
what was left: the elapsed times and jobs of those runs add up (each run is listed in the file);
``--after <name>.snakemake.log`` adds an interrupted run whose finished jobs the next run kept.
Disk use is measured per top-level directory the workflow writes (data, work, results, logs,
benchmarks/out). The jobs' own Snakemake benchmark files (benchmarks/out/**/*.tsv) give the CPU
and wall seconds the jobs held, in all and per folder of job kind. ``omnilidar docs`` writes
docs/troubleshooting.md's block from the file, so the numbers there come from a measured run, not
from hand.

With ``--reference DIR`` (an earlier run of the same target in another clone) the jobs both runs
have are compared, per ``--group NAME=GLOB`` of benchmark files (default: one group per folder):
their wall seconds here and there and the ratio. A group whose code did not change between the two
commits measures how fast the machine was that day; the others, that and what the change did.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import re
import subprocess
from datetime import datetime
from pathlib import Path

STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$", re.M)
OUTPUT_DIRS = ("data", "work", "results", "logs", "benchmarks/out")


def log_that_built(run_dir: Path, target: str) -> Path:
    for log in sorted((run_dir / ".snakemake" / "log").glob("*.snakemake.log")):
        text = log.read_text()
        if re.search(rf"output: .*{re.escape(target)}", text) and "Finished jobid" in text:
            return log
    raise SystemExit(f"{run_dir}: no Snakemake log built {target}")


def elapsed(log: Path) -> tuple[float, int]:
    text = log.read_text()
    stamps = [datetime.strptime(s, "%a %b %d %H:%M:%S %Y") for s in STAMP.findall(text)]
    return (stamps[-1] - stamps[0]).total_seconds(), text.count("Finished jobid")


def disk_mb(path: Path) -> float:
    if not path.exists():
        return 0.0
    out = subprocess.run(["du", "-sk", str(path)], capture_output=True, text=True, check=True).stdout
    return round(int(out.split()[0]) / 1024, 1)


def job_walls(run_dir: Path) -> dict[str, float]:
    """Wall seconds of each job, by its benchmark file relative to benchmarks/out."""
    root = run_dir / "benchmarks" / "out"
    return {str(tsv.relative_to(root)): float(bench_row(tsv)["s"]) for tsv in sorted(root.rglob("*.tsv"))}


def bench_row(tsv: Path) -> dict[str, str]:
    """A Snakemake benchmark file's last row, by column name."""
    lines = tsv.read_text().strip().splitlines()
    return dict(zip(lines[0].split("\t"), lines[-1].split("\t")))


def against_reference(run_dir: Path, reference: Path, groups: list[str], commit: str | None) -> dict:
    """The jobs both runs have, per group of benchmark files: wall seconds here, there, and the ratio."""
    here, there = job_walls(run_dir), job_walls(reference)
    common = sorted(set(here) & set(there))
    named = [g.split("=", 1) for g in groups] or sorted({(n.rsplit("/", 1)[0],) * 2 for n in common})
    out = {}
    for name, pattern in named:
        jobs = [n for n in common if fnmatch.fnmatch(n, pattern) or n.startswith(f"{pattern}/")]  # a glob or a folder
        if jobs:
            a, b = sum(here[n] for n in jobs), sum(there[n] for n in jobs)
            out[name] = {"jobs": len(jobs), "wall": round(a, 1), "reference_wall": round(b, 1), "ratio": round(a / b, 3)}
    return {"commit": commit, "groups": out}


def job_seconds(run_dir: Path) -> dict:
    """CPU and wall seconds of the run's jobs from their benchmark files, in all and per folder."""
    groups: dict[str, dict[str, float]] = {}
    for tsv in sorted((run_dir / "benchmarks" / "out").rglob("*.tsv")):
        row = bench_row(tsv)
        group = str(tsv.parent.relative_to(run_dir / "benchmarks" / "out"))
        g = groups.setdefault(group, {"jobs": 0, "cpu": 0.0, "wall": 0.0})
        g["jobs"] += 1
        g["cpu"] += float(row["cpu_time"])
        g["wall"] += float(row["s"])
    rounded = {k: {"jobs": v["jobs"], "cpu": round(v["cpu"], 1), "wall": round(v["wall"], 1)} for k, v in groups.items()}
    return {"cpu": round(sum(v["cpu"] for v in groups.values()), 1),
            "wall": round(sum(v["wall"] for v in groups.values()), 1), "by_folder": rounded}


def git_commit(run_dir: Path) -> str:
    return subprocess.run(["git", "-C", str(run_dir), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run-dir", type=Path, required=True, help="the clone the run happened in")
    ap.add_argument("--target", default="results/semkitti_1pct.json")
    ap.add_argument("--after", action="append", default=[],
                    help="a target the clone built first, in a run of its own, or the log name of an "
                         "interrupted run whose finished jobs the last run kept (repeat, in order)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--machine", default=f"a {os.cpu_count()}-core CPU machine",
                    help="where the run happened, as the docs name it (default: this machine's cores)")
    ap.add_argument("--commit", default=None, help="the run's commit where the run directory has no git history")
    ap.add_argument("--reference", type=Path, default=None,
                    help="an earlier run of the same target (its clone): compare the jobs both have")
    ap.add_argument("--group", action="append", default=[],
                    help="NAME=GLOB of benchmark files under benchmarks/out compared with --reference (repeat; "
                         "default: one group per folder)")
    args = ap.parse_args()
    runs = []
    for target in args.after + [args.target]:
        interrupted = target.endswith(".snakemake.log")  # a run stopped before it built anything asked for
        log = args.run_dir / ".snakemake" / "log" / target if interrupted else log_that_built(args.run_dir, target)
        seconds, jobs = elapsed(log)
        runs.append({"target": None if interrupted else target, "log": log.name, "elapsed_seconds": seconds,
                     "jobs": jobs})
    commit = git_commit(args.run_dir) or args.commit
    doc = {"experiment": "run_cost", "target": args.target, "commit": commit, "machine": args.machine,
           "log": runs[-1]["log"],
           "elapsed_seconds": sum(r["elapsed_seconds"] for r in runs), "jobs": sum(r["jobs"] for r in runs)}
    if args.after:
        doc["runs"] = runs
    doc |= {"disk_mb": {d: disk_mb(args.run_dir / d) for d in OUTPUT_DIRS}, "job_seconds": job_seconds(args.run_dir)}
    if args.reference:
        doc["against_reference"] = against_reference(args.run_dir, args.reference, args.group,
                                                     git_commit(args.reference))
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
