"""Real dataset roots are tracked by their listing; package versions are reported, and
rerun stages only where ``rerun_on_version_change`` asks for it. Real runs of the index
stage on a small real-format SemanticKITTI root written here."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest
import yaml

from omnilidar.io.semantickitti import write_label, write_points
from workflow_helpers import copy_workflow, planned_jobs, rerun_reasons, snakemake

INDEX = "data/index/semantickitti.json"


def _write_scan(root, seq, frame, seed):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-20, 20, (64, 4)).astype(np.float32)
    pts[:, 3] = rng.uniform(0, 1, 64)
    seq_dir = root / "sequences" / seq
    write_points(seq_dir / "velodyne" / f"{frame:06d}.bin", pts)
    write_label(seq_dir / "labels" / f"{frame:06d}.label", rng.choice([40, 48, 10], 64).astype(np.uint32))


@pytest.fixture()
def real_root_workflow(tmp_path):
    (tmp_path / "wf").mkdir()
    wd = copy_workflow(tmp_path / "wf")
    root = tmp_path / "semantickitti"
    for seq in ("00", "08"):
        for frame in range(2):
            _write_scan(root, seq, frame, seed=int(seq) * 10 + frame)
    cfg = wd / "real.yaml"
    cfg.write_text(yaml.safe_dump({"datasets": {"semantickitti": {"root": str(root)}}}))
    snakemake(wd, INDEX, "--configfile", str(cfg))
    return wd, root, ("--configfile", str(cfg))


def _train_count(wd) -> int:
    return len(json.loads((wd / INDEX).read_text())["splits"]["train"])


@pytest.mark.slow
def test_adding_replacing_and_removing_real_scans_reindexes(real_root_workflow):
    wd, root, cfg = real_root_workflow
    assert planned_jobs(wd, INDEX, *cfg) == {}
    assert _train_count(wd) == 2

    _write_scan(root, "00", 2, seed=99)  # a new scan and its label
    assert planned_jobs(wd, INDEX, *cfg) == {"index_dataset": 1}
    assert "params" in rerun_reasons(wd, INDEX, *cfg).lower()
    snakemake(wd, INDEX, *cfg)
    assert _train_count(wd) == 3 and planned_jobs(wd, INDEX, *cfg) == {}

    # The same label file rewritten with other labels (same size, newer time).
    label = root / "sequences" / "00" / "labels" / "000001.label"
    time.sleep(0.01)
    label.write_bytes(np.full(64, 40, np.uint32).tobytes())
    assert planned_jobs(wd, INDEX, *cfg) == {"index_dataset": 1}
    snakemake(wd, INDEX, *cfg)

    # The labeler, which trains on the index, reruns when the root changes.
    assert "train_labeler" in planned_jobs(wd, "data/labeler/semantickitti.pt", *cfg)
    for f in ("velodyne/000002.bin", "labels/000002.label"):
        os.remove(root / "sequences" / "00" / f)
    assert planned_jobs(wd, INDEX, *cfg) == {"index_dataset": 1}
    snakemake(wd, INDEX, *cfg)
    assert _train_count(wd) == 2


@pytest.mark.slow
def test_version_changes_are_reported_and_rerun_only_where_asked(real_root_workflow):
    wd, _, cfg = real_root_workflow
    record = wd / ".snakemake" / "omnilidar_versions.json"
    versions = json.loads(record.read_text())  # written by the successful run
    assert versions["torch"] and "spconv" in versions and "mambapy" in versions
    record.write_text(json.dumps(dict(versions, torch="0.0.1")))

    out = rerun_reasons(wd, INDEX, *cfg)
    assert f"Package versions changed since the last run: torch 0.0.1 -> {versions['torch']}" in out
    assert "outputs are kept" in out
    assert planned_jobs(wd, INDEX, *cfg) == {}

    asked = wd / "versions.yaml"
    doc = yaml.safe_load((wd / "real.yaml").read_text())
    asked.write_text(yaml.safe_dump(dict(doc, rerun_on_version_change=["index-dataset"])))
    assert planned_jobs(wd, INDEX, "--configfile", str(asked)) == {"index_dataset": 1}
    assert planned_jobs(wd, "data/subsets/semantickitti_1pct.json", "--configfile", str(asked)) == {
        "index_dataset": 1, "make_subset": 1}
    asked.write_text(yaml.safe_dump(dict(doc, rerun_on_version_change=["train-generator"])))
    assert planned_jobs(wd, INDEX, "--configfile", str(asked)) == {}


@pytest.mark.slow
def test_a_failed_stage_shows_its_error_line_on_the_terminal(real_root_workflow):
    """A truncated .bin under a real root: the index stage fails, and the terminal shows the one
    line naming the file and the problem (not only the path of the job's log)."""
    wd, root, cfg = real_root_workflow
    bad = root / "sequences" / "00" / "velodyne" / "000001.bin"
    bad.write_bytes(bad.read_bytes()[:-6])
    out = snakemake(wd, INDEX, *cfg, check=False)
    assert out.returncode != 0
    terminal = out.stdout + out.stderr
    assert "logs/index/semantickitti.log: omnilidar index-dataset: error:" in terminal
    assert f"{bad}" in terminal and "is not a positive multiple of 16" in terminal
