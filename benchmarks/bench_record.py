"""A benchmark's figures as a result file, so docs/benchmarks.md is written from it (`omnilidar docs`)
instead of by hand: each benchmark takes ``--out docs/results/bench_<name>.json`` and records the
rows of its table (what, median, target) beside its raw figures, the command that made them, the
commit and the machine."""

from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path


def out_arg(parser) -> None:
    parser.add_argument("--out", type=Path, default=None,
                        help="also write the figures as a result file (docs/results/bench_<name>.json)")


def _command() -> str:
    """The command as run, without --out (so a page quotes what to type to measure it again)."""
    argv, skip = [], False
    for arg in sys.argv[1:]:
        if skip:
            skip = False
        elif arg == "--out":
            skip = True
        elif not arg.startswith("--out="):
            argv.append(arg)
    script = Path(sys.argv[0]).resolve().relative_to(Path(__file__).resolve().parents[1])
    return shlex.join(["python", script.as_posix(), *argv])  # quoted where an argument has spaces


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], capture_output=True, text=True, cwd=Path(__file__).parent).stdout.rstrip("\n")


def _commit() -> str | None:
    """The commit measured, with the tracked files changed since named; docs/ does not count (a
    benchmark run rewrites its result files there, and no benchmark reads the pages)."""
    head = _git("rev-parse", "--short", "HEAD") or None
    changed = [line[3:] for line in _git("status", "--porcelain", "--untracked-files=no").splitlines()
               if not line[3:].startswith("docs/")]
    return f"{head} + uncommitted {', '.join(changed)}" if head and changed else head


def write(out: Path | None, rows: list[dict], figures: dict, columns: list[str] | None = None,
          machine: dict | None = None) -> None:
    """Write the result file when ``--out`` was given. ``rows``: one dict of strings per table row,
    keyed by ``columns`` (default what, median, target); ``figures``: the raw numbers behind them;
    ``machine``: where the figures were measured, when not on this machine (read from a run's logs)."""
    if out is None:
        return
    import torch

    commit = _commit()
    doc = {"experiment": Path(out).stem, "command": _command(), "commit": commit,
           "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
           "machine": {"cpus": len(os.sched_getaffinity(0)), "processor": platform.processor() or platform.machine(),
                       "torch": torch.__version__, "python": platform.python_version()},
           "rows": rows, "figures": figures}
    if torch.cuda.is_available():  # the accelerator the figures were measured on, by name
        doc["machine"]["gpu"] = torch.cuda.get_device_name(0)
    if machine is not None:
        doc["machine"] = machine
    if columns is not None:
        doc["columns"] = list(columns)
    Path(out).write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {out}")


def print_table(rows: list[dict], columns: list[str]) -> None:
    """The rows on the terminal, one line each, cells joined by " | " under a header line."""
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join(str(row[c]) for c in columns))
