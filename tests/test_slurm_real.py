"""The SLURM profile on a real single-node SLURM (workflow/profiles/slurm/single-node.sh).

CPU-only pass: with resources.gpus false the test configuration's headline target runs through
the profile, every job on the cpu partition with no GPU asked, and its result equals a local
run's. GRES pass: on a node that declares a GPU, a GPU rule lands on the gpu partition. The
daemons are started and stopped by the test, by their process ids. Skipped where SLURM and munge
are not installed or the test does not run as root (slurmd starts jobs).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from workflow_helpers import ROOT, copy_workflow, snakemake

SCRIPT = ROOT / "workflow" / "profiles" / "slurm" / "single-node.sh"
TARGET = "results/semkitti_1pct.json"
# The test configuration with a shorter labeler: both runs use it, so they still compare.
FAST = "downstream: {labeler: {schedule: {iterations: 10}}}\n"
VOLATILE = {"timings", "created", "seconds", "train_seconds"}

_SBIN = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/sbin"])
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(os.environ.get("OMNILIDAR_SKIP_REAL_SLURM") == "1", reason="OMNILIDAR_SKIP_REAL_SLURM=1"),
    pytest.mark.skipif(not all(shutil.which(t, path=_SBIN) for t in ("munged", "slurmctld", "slurmd", "sbatch")),
                       reason="no SLURM here (apt-get install slurmctld slurmd munge)"),
    pytest.mark.skipif(os.geteuid() != 0, reason="slurmd must run as root"),
]


class SingleNode:
    """A running single-node SLURM in ``path``; ``env`` points its clients at it."""

    def __init__(self, path: Path, gpu: bool):
        self.path = path
        cmd = ["bash", str(SCRIPT), "up", str(path)] + (["--gpu"] if gpu else [])
        up = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, PATH=_SBIN))
        assert up.returncode == 0, up.stdout + up.stderr
        self.env = {"SLURM_CONF": str(path / "slurm.conf"), "PATH": _SBIN}

    def jobs(self) -> list[dict]:
        """Every job the cluster ran (MinJobAge keeps them in squeue): rule, partition, GRES."""
        out = subprocess.run(["squeue", "-t", "all", "-h", "-o", "%k|%P|%b|%T"], capture_output=True, text=True,
                             env=dict(os.environ, **self.env), check=True).stdout
        rows = [line.split("|") for line in out.splitlines() if line.strip()]
        return [{"rule": c.removeprefix("rule_").split("_wildcards")[0], "partition": p, "gres": g, "state": s}
                for c, p, g, s in rows]

    def down(self) -> None:
        subprocess.run(["bash", str(SCRIPT), "down", str(self.path)], check=True)
        for pidfile in ("slurmctld.pid", "slurmd.pid", "munged.pid"):
            assert not (self.path / pidfile).exists()


def _cluster_overlay(path: Path, cluster: Path, gpus) -> Path:
    path.write_text(FAST + f"resources: {{gpus: {json.dumps(gpus)}, partition_config: {cluster / 'partitions.yaml'}}}\n")
    return path


def _stable(result: dict) -> dict:
    """A result without what differs between two runs of the same work (times, dates)."""
    if isinstance(result, dict):
        return {k: _stable(v) for k, v in result.items() if k not in VOLATILE}
    if isinstance(result, list):
        return [_stable(v) for v in result]
    return result


def _profile_run(workdir: Path, cluster: SingleNode, overlay: Path, *targets: str):
    old = {k: os.environ.get(k) for k in cluster.env}
    os.environ.update(cluster.env)
    try:
        return snakemake(workdir, "--workflow-profile", "workflow/profiles/slurm", "--configfile", "config/test.yaml",
                         str(overlay), "--slurm-status-command", "squeue",
                         "--slurm-init-seconds-before-status-checks", "1", *targets)
    finally:
        for k, v in old.items():
            os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)


def test_headline_target_through_the_profile_on_a_cpu_only_slurm_equals_the_local_run(tmp_path):
    local = copy_workflow(tmp_path / "local")
    (tmp_path / "fast.yaml").write_text(FAST)
    snakemake(local, "--configfile", "config/test.yaml", str(tmp_path / "fast.yaml"), "--", TARGET)

    cluster = SingleNode(tmp_path / "slurm", gpu=False)
    try:
        wd = copy_workflow(tmp_path / "cluster")
        overlay = _cluster_overlay(tmp_path / "cpu_only.yaml", cluster.path, False)
        _profile_run(wd, cluster, overlay, "--", TARGET)
        jobs = cluster.jobs()
    finally:
        cluster.down()

    assert len(jobs) >= 10 and {j["state"] for j in jobs} == {"COMPLETED"}, jobs
    assert {"train_generator", "train_labeler", "train_supervised", "train_gda"} <= {j["rule"] for j in jobs}
    assert {j["partition"] for j in jobs} == {"cpu"} and not any("gpu" in j["gres"] for j in jobs), jobs
    ours, theirs = (json.loads((d / TARGET).read_text()) for d in (wd, local))
    assert _stable(ours) == _stable(theirs)


def test_gpu_rules_land_on_the_gpu_partition_of_a_gres_node(tmp_path):
    cluster = SingleNode(tmp_path / "slurm", gpu=True)
    try:
        wd = copy_workflow(tmp_path / "cluster")
        overlay = _cluster_overlay(tmp_path / "auto.yaml", cluster.path, "auto")
        # The prompts (text device cpu in the test config) and the domains on the CPU, the generator on the GPU node.
        _profile_run(wd, cluster, overlay, "--", "data/generator/full/model.pt")
        jobs = cluster.jobs()
    finally:
        cluster.down()
    by_rule = {}
    for j in jobs:
        by_rule.setdefault(j["rule"], []).append(j)
    assert {j["state"] for j in jobs} == {"COMPLETED"}, jobs
    assert [(j["partition"], j["gres"]) for j in by_rule["train_generator"]] == [("gpu", "gres:gpu:1")], jobs
    assert all(j["partition"] == "cpu" for j in by_rule["build_domain"] + by_rule["synthesize"]), jobs
