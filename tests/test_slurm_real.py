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
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from workflow_helpers import ROOT, copy_workflow, snakemake

SCRIPT = ROOT / "workflow" / "profiles" / "slurm" / "single-node.sh"
TARGET = "results/semkitti_1pct.json"
GENERATOR = "data/generator/full/model.pt"
SUMMARY = "results/data_summary.json"  # a CPU rule the headline target does not make
# The test configuration with tiny trainings (the students run the embedded default's 200
# iterations otherwise) and one seed per backbone, so that the ~27 cluster jobs (index, subset and
# result assembly are local rules) go through SLURM in a few minutes: both runs use it, so they
# still compare.
FAST = ("downstream: {voxel_size: 0.8, schedule: {iterations: 3, log_interval: 1, checkpoint_interval: 2},\n"
        "             labeler: {voxel_size: 0.8, schedule: {iterations: 10, log_interval: 1}},\n"
        "             experiments: {semkitti: {seeds: 1}}}\n")
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
        # Six job slots on the CI machine's cores: the tiny jobs mostly start up and wait.
        cmd = ["bash", str(SCRIPT), "up", str(path), "--cpus", "6"] + (["--gpu"] if gpu else [])
        up = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, PATH=_SBIN))
        if up.returncode != 0:
            # The machine cannot run the daemons (a container without the rights, a SLURM of its own):
            # no cluster to test on here, which says nothing of the profile.
            subprocess.run(["bash", str(SCRIPT), "down", str(path)], capture_output=True)
            pytest.skip(f"no single-node SLURM on this machine: {(up.stderr or up.stdout).strip()[-300:]}")
        self.env = {"SLURM_CONF": str(path / "slurm.conf"), "PATH": _SBIN}

    def jobs(self) -> list[dict]:
        """Every job the cluster ran (MinJobAge keeps them in squeue): rule, partition, GPUs asked."""
        out = subprocess.run(["squeue", "-t", "all", "-h", "-O", "Comment:|,Partition:|,tres-per-job:|,State:"],
                             capture_output=True, text=True,
                             env=dict(os.environ, **self.env), check=True).stdout
        rows = [[f.strip() for f in line.split("|")] for line in out.splitlines() if line.strip()]
        return [{"rule": c.removeprefix("rule_").split("_wildcards")[0], "partition": p, "gres": g, "state": s}
                for c, p, g, s in rows]

    def down(self) -> None:
        subprocess.run(["bash", str(SCRIPT), "down", str(self.path)], check=True)
        for pidfile in ("slurmctld.pid", "slurmd.pid", "munged.pid"):
            assert not (self.path / pidfile).exists()


def _workflow_copy(path: Path) -> Path:
    path.mkdir(parents=True)
    return copy_workflow(path)


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
    return snakemake(workdir, "--workflow-profile", "workflow/profiles/slurm", "--configfile", "config/test.yaml",
                     str(overlay), "--slurm-status-command", "squeue",
                     "--slurm-init-seconds-before-status-checks", "1", *targets,
                     env=cluster.env)


def test_headline_target_on_a_cpu_only_slurm_equals_the_local_run_and_gpu_rules_land_on_a_gres_node(tmp_path):
    # The local run goes on beside the cluster pass (which mostly waits on the scheduler).
    local = _workflow_copy(tmp_path / "local")
    (tmp_path / "fast.yaml").write_text(FAST)
    local_run = ThreadPoolExecutor(1).submit(snakemake, local, "--configfile", "config/test.yaml",
                                             str(tmp_path / "fast.yaml"), "--", TARGET)

    # CPU-only pass: resources.gpus false on a node without GPUs.
    wd = _workflow_copy(tmp_path / "cluster")
    cluster = SingleNode(tmp_path / "slurm", gpu=False)
    try:
        _profile_run(wd, cluster, _cluster_overlay(tmp_path / "cpu_only.yaml", cluster.path, False), "--", TARGET)
        jobs = cluster.jobs()
    finally:
        cluster.down()
        local_run.result()
    assert len(jobs) >= 10 and {j["state"] for j in jobs} == {"COMPLETED"}, jobs
    assert {"train_generator", "train_labeler", "train_supervised", "train_gda"} <= {j["rule"] for j in jobs}
    # Listing and assembly are local rules: they ran beside Snakemake, not through the queue.
    assert not {"index_dataset", "make_subset", "semkitti_result"} & {j["rule"] for j in jobs}, jobs
    assert {j["partition"] for j in jobs} == {"cpu"} and not any("gpu" in j["gres"] for j in jobs), jobs
    ours, theirs = (json.loads((d / TARGET).read_text()) for d in (wd, local))
    assert _stable(ours) == _stable(theirs)

    # GRES pass: resources.gpus auto on a node that declares a GPU; the generator (device auto)
    # retrains there and lands on the gpu partition with one GPU, a CPU rule stays on cpu.
    cluster = SingleNode(tmp_path / "slurm_gpu", gpu=True)
    try:
        _profile_run(wd, cluster, _cluster_overlay(tmp_path / "auto.yaml", cluster.path, "auto"),
                     "--forcerun", "train_generator", "--", GENERATOR, SUMMARY)
        jobs = cluster.jobs()
    finally:
        cluster.down()
    assert {j["state"] for j in jobs} == {"COMPLETED"}, jobs
    where = {j["rule"]: (j["partition"], j["gres"]) for j in jobs}
    assert where["train_generator"] == ("gpu", "gres:gpu:1"), jobs
    assert where["data_summary"] == ("cpu", "N/A"), jobs
