"""Run Snakemake on a copy of the workflow and read its dry-run plans."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WORKFLOW_PARTS = ("Snakefile", "rules", "workflow", "config", "omnilidar")


def copy_workflow(dest: Path) -> Path:
    """A private copy of the workflow and package, so tests can edit code and
    config and run Snakemake without touching the checkout."""
    for part in WORKFLOW_PARTS:
        src = ROOT / part
        if src.is_dir():
            shutil.copytree(src, dest / part, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(src, dest / part)
    return dest


def embedded_default(workdir: Path) -> dict:
    """The workflow copy's config/config.yaml (the embedded default), as written."""
    import yaml

    return yaml.safe_load((workdir / "config" / "config.yaml").read_text())


def limits_overlay(folder: Path, gpu_runtime: str, cpu_runtime: str, extra: str = "") -> Path:
    """A config overlay pointing resources.partition_config at a partition file with these time
    limits (and a typical node's memory, CPUs and GPUs); ``extra``: more resources keys."""
    parts = folder / f"partitions_{gpu_runtime}_{cpu_runtime}.yaml".replace(":", "")
    parts.write_text("partitions:\n"
                     f"  gpu: {{max_runtime: '{gpu_runtime}', max_mem_mb: 512000, max_cpus_per_task: 64, max_gpu: 8}}\n"
                     f"  cpu: {{max_runtime: '{cpu_runtime}', max_mem_mb: 256000, max_cpus_per_task: 64, max_gpu: 0}}\n")
    overlay = parts.with_name(parts.stem + "_overlay.yaml")
    overlay.write_text(f"resources: {{{extra}partition_config: {parts}}}\n")
    return overlay


def whole_and_chained(tmp_path: Path, run_config: str, target: str, chain_resources: str, made: tuple[str, ...]):
    """Make ``target`` in a copy of the workflow (config/test.yaml + ``run_config``), then copy that
    tree without the ``made`` folders, to be made again as a segment chain under 30-minute
    partitions (``chain_resources``: resources keys that make the training outlast them).
    Returns (whole tree, chained tree, run config arguments, chain config arguments)."""
    (tmp_path / "run.yaml").write_text(run_config)
    run = ("--configfile", "config/test.yaml", str(tmp_path / "run.yaml"))
    chain = (*run, str(limits_overlay(tmp_path, "00:30:00", "00:30:00", chain_resources)))
    (tmp_path / "whole").mkdir()
    whole = copy_workflow(tmp_path / "whole")
    snakemake(whole, *run, "--", target)
    chained = tmp_path / "chained"
    shutil.copytree(whole, chained, symlinks=True)
    for folder in made:
        shutil.rmtree(chained / folder)
    return whole, chained, run, chain


def snakemake(workdir: Path, *args: str, check: bool = True, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run snakemake in ``workdir`` with that directory's package copy first on the path
    (``env``: variables to set besides)."""
    env = dict(os.environ, **(env or {}), PYTHONPATH=str(workdir), PYTHONDONTWRITEBYTECODE="1")
    cmd = [sys.executable, "-m", "snakemake", "--cores", "2", *args]
    out = subprocess.run(cmd, cwd=workdir, env=env, capture_output=True, text=True)
    if check and out.returncode != 0:
        raise AssertionError(f"snakemake {' '.join(args)} failed:\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}")
    return out


def planned_jobs(workdir: Path, *args: str) -> dict[str, int]:
    """Job counts per rule of a dry run (empty when nothing needs to run)."""
    out = snakemake(workdir, "--dry-run", *args, "--quiet", "rules")
    text = out.stdout + out.stderr
    counts: dict[str, int] = {}
    block = text.split("Job stats:", 1)
    if len(block) < 2:
        return counts
    for line in block[1].splitlines():
        m = re.match(r"^([A-Za-z_][\w]*)\s+(\d+)\s*$", line.strip())
        if m and m.group(1) != "total":
            counts[m.group(1)] = int(m.group(2))
    return counts


def planned_job_wildcards(workdir: Path, *args: str) -> list[tuple[str, dict[str, str]]]:
    """(rule, wildcards) of every job of a dry run."""
    out = snakemake(workdir, "--dry-run", *args)
    jobs = []
    for block in re.split(r"\n(?=(?:local)?rule \w+:)", out.stdout + out.stderr):
        rule = re.match(r"(?:local)?rule (\w+):", block)
        if rule:
            found = re.search(r"^\s+wildcards: (.*)$", block, re.M)
            wildcards = dict(kv.split("=", 1) for kv in found.group(1).split(", ")) if found else {}
            jobs.append((rule.group(1), wildcards))
    return jobs


def synthesized_shards(workdir: Path, *args: str) -> dict[str, int]:
    """Synthesize jobs (shards) of a dry run per dataset; empty when none."""
    jobs = planned_job_wildcards(workdir, *args)
    return dict(Counter(w["dataset"] for rule, w in jobs if rule == "synthesize"))


def rerun_reasons(workdir: Path, *args: str) -> str:
    out = snakemake(workdir, "--dry-run", *args)
    return out.stdout + out.stderr


# Stands in for the omnilidar CLI in the rerun tests: creates the outputs named by
# --out / --figure (a directory when the name has no file suffix), so that Snakemake
# runs every job for real and records its params, quickly.
FAKE_CLI = """#!{python}
import sys
from pathlib import Path
args = sys.argv[1:]
for flag in ("--out", "--figure"):
    if flag in args:
        p = Path(args[args.index(flag) + 1])
        if p.suffix in (".json", ".pt", ".png", ".npz", ".pkl", ".html"):
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text("{{}}")
        else:
            p.mkdir(parents=True, exist_ok=True)
"""


def run_with_fake_cli(workdir: Path, bin_dir: Path, *args: str) -> None:
    """Run Snakemake on ``args`` (targets, --configfile ...) with the fake CLI first on PATH."""
    bin_dir.mkdir(parents=True, exist_ok=True)
    fake = bin_dir / "omnilidar"
    fake.write_text(FAKE_CLI.format(python=sys.executable))
    fake.chmod(0o755)
    env = dict(os.environ, PYTHONPATH=str(workdir), PYTHONDONTWRITEBYTECODE="1",
               PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    out = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", *args], cwd=workdir, env=env,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]


def plan_with_change(workdir: Path, config_file: Path, change: dict, *targets: str) -> dict[str, int]:
    """Jobs a dry run plans for ``targets`` after ``change`` ({dotted.key: value}) is applied to
    ``config_file`` (written as changed.yaml beside it)."""
    import yaml

    doc = yaml.safe_load(config_file.read_text())
    for dotted, value in change.items():
        node = doc
        *parents, leaf = dotted.split(".")
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = value
    changed = workdir / "changed.yaml"
    changed.write_text(yaml.safe_dump(doc))
    return planned_jobs(workdir, *targets, "--configfile", str(changed))
