"""The Snakemake workflow: lint, DAG shape, profiles, real runs and reruns."""

from __future__ import annotations

import re

import pytest
import yaml

from omnilidar.config import load_config
from workflow_helpers import copy_workflow, planned_jobs, rerun_reasons, snakemake

TINY = "config/test.yaml"
DATASETS = ("semantickitti", "kitti360", "pi3det", "nuscenes")


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return copy_workflow(tmp_path_factory.mktemp("wf"))


def _shard_counts(config: dict) -> dict[str, int]:
    synth = config["synthetic"]["datasets"]
    return {
        "synthesize_semantickitti": len(synth["semantickitti"]["sequences"]),
        "synthesize_kitti360": len(synth["kitti360"]["sequences"]),
        "synthesize_pi3det": len(synth["pi3det"]["platforms"]),
        "synthesize_nuscenes": len(synth["nuscenes"]["splits"]),
    }


def test_lint_is_clean(workdir):
    out = snakemake(workdir, "--lint", check=False)
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.mark.parametrize("configfile", ["config/config.yaml", TINY])
def test_data_summary_dag_has_one_job_per_shard(workdir, configfile):
    config = load_config(workdir / configfile)
    jobs = planned_jobs(workdir, "results/data_summary.json", "--configfile", configfile)
    expected = {**_shard_counts(config), "index_dataset": 4, "data_summary": 1}
    assert jobs == expected
    # Sharded, not one job per scan: the embedded default stays a small DAG.
    assert sum(jobs.values()) < 60


def test_embedded_default_job_counts_are_pinned(workdir):
    jobs = planned_jobs(workdir, "results/data_summary.json")
    assert jobs["synthesize_semantickitti"] == 13  # sequences 00-12: train, val 08, two test
    assert jobs["index_dataset"] == 4


def test_real_roots_are_indexed_not_generated(workdir, tmp_path):
    cfg = tmp_path / "real.yaml"
    cfg.write_text(yaml.safe_dump({"datasets": {d: {"root": str(tmp_path / d)} for d in DATASETS}}))
    jobs = planned_jobs(workdir, "results/data_summary.json", "--configfile", str(cfg))
    assert jobs == {"index_dataset": 4, "data_summary": 1}


def test_unknown_config_key_fails_before_any_job(workdir, tmp_path):
    cfg = tmp_path / "typo.yaml"
    cfg.write_text("synthetic_typo: 1\n")
    out = snakemake(workdir, "--dry-run", "results/data_summary.json", "--configfile", str(cfg), check=False)
    assert out.returncode != 0
    assert "synthetic_typo" in out.stdout + out.stderr


def test_slurm_profile_dry_run(workdir):
    out = snakemake(workdir, "--dry-run", "results/data_summary.json", "--workflow-profile",
                    "workflow/profiles/slurm")
    assert "synthesize_semantickitti" in out.stdout + out.stderr


@pytest.mark.slow
def test_data_stage_runs_and_reruns_only_what_changed(tmp_path, real_data):
    wd = copy_workflow(tmp_path)
    cfg = yaml.safe_load((wd / TINY).read_text())
    cfg["data_summary"]["reference_scans"] = [str(p) for p in sorted(real_data.glob("kitti_object/velodyne/*.bin"))]
    (wd / TINY).write_text(yaml.safe_dump(cfg))
    target = ("results/data_summary.json", "--configfile", TINY)
    snakemake(wd, *target)
    summary = yaml.safe_load((wd / "results" / "data_summary.json").read_text())
    assert summary["experiment"] == "data_summary"
    assert summary["data_source"]["semantickitti"] == "synthetic"
    real = summary["groups"]["real_kitti_reference"]["points_per_scan"]["mean"]
    synthetic = summary["groups"]["semantickitti"]["points_per_scan"]["mean"]
    assert 0.7 < synthetic / real < 1.3, "synthetic HDL-64 scans should hold about as many points as KITTI's"
    assert (wd / "results" / "figures" / "data_summary.png").stat().st_size > 1000
    assert planned_jobs(wd, *target) == {}, "a finished workflow plans nothing"

    # A comment and a docstring in the synthetic world's code: nothing reruns.
    f = wd / "omnilidar" / "data" / "synthetic" / "raycast.py"
    text = f.read_text()
    assert text.startswith('"""')
    f.write_text(text.replace('"""', '"""Edited docstring. ', 1).replace("\n\n", "\n\n# an edited comment\n", 1))
    assert planned_jobs(wd, *target) == {}

    # Code of the index stage: index and summary rerun, generation does not.
    index_py = wd / "omnilidar" / "data" / "index.py"
    index_py.write_text(index_py.read_text() + "\n_EDITED = True\n")
    jobs = planned_jobs(wd, *target)
    assert set(jobs) == {"index_dataset", "data_summary"}, jobs
    snakemake(wd, *target)

    # Settings of the summary only: only the summary reruns.
    cfg = yaml.safe_load((wd / TINY).read_text())
    cfg.setdefault("data_summary", {})["max_scans"] = 3
    (wd / TINY).write_text(yaml.safe_dump(cfg))
    assert planned_jobs(wd, *target) == {"data_summary": 1}
    reasons = rerun_reasons(wd, *target)
    assert re.search(r"reason: .*[Pp]arams", reasons)

    # Settings of the synthetic world: every generation job and everything downstream.
    cfg["synthetic"]["world"] = dict(cfg["synthetic"].get("world", {}))
    cfg["seed"] = cfg.get("seed", 0) + 1
    (wd / TINY).write_text(yaml.safe_dump(cfg))
    jobs = planned_jobs(wd, *target)
    assert jobs == {**_shard_counts(load_config(wd / TINY)), "index_dataset": 4, "data_summary": 1}
