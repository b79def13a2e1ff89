"""Reruns recompute for real: the generator, the labeler and a segmentor on the tiny config.

Each trainer keeps resumable state in an undeclared work folder. These tests run the
workflow (no fakes), then change things the way a user would and check what the
trainers actually do: an upstream code constant that changes their data retrains them
from scratch (new weights, and the log says so), more iterations resume, a comment
reruns nothing, and a copied tree resumes from its own state only.
"""

from __future__ import annotations

import hashlib
import shutil

import pytest
import yaml

from workflow_helpers import copy_workflow, planned_jobs, snakemake

TINY = "config/test.yaml"
GENERATOR = "data/generator/full/model.pt"
LABELER = "data/labeler/semantickitti.pt"
SEGMENTOR = "data/segmentation/semantickitti/minkunet_1pct_real.pt"
TARGETS = (GENERATOR, LABELER, SEGMENTOR)
LOGS = {GENERATOR: "logs/generator/train_full.log", LABELER: "logs/downstream/labeler.log",
        SEGMENTOR: "logs/downstream/train/semantickitti_minkunet_1pct_real.log"}


def _md5(path) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


def _config(wd, generator_iterations=3, seg_iterations=3):
    """The tiny test config with tiny downstream schedules too."""
    cfg = yaml.safe_load((wd / TINY).read_text())
    cfg["generator"]["training"]["iterations"] = generator_iterations
    tiny = {"iterations": seg_iterations, "log_interval": 1, "checkpoint_interval": 2, "warmup_iters": 1}
    cfg["downstream"] = {**cfg.get("downstream", {}), "voxel_size": 0.8, "schedule": tiny,
                         "labeler": {"voxel_size": 0.8, "schedule": tiny}}
    path = wd / "rerun.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return ("--configfile", str(path))


def _edit(path, old, new):
    text = path.read_text()
    assert old in text, f"{old!r} not in {path}"
    path.write_text(text.replace(old, new, 1))


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    wd = copy_workflow(tmp_path_factory.mktemp("reruns"))
    cfg = _config(wd)
    snakemake(wd, *TARGETS, *cfg)
    return wd, cfg


@pytest.mark.slow
def test_comments_rerun_nothing_and_code_constants_retrain_from_scratch(finished):
    wd, cfg = finished
    assert planned_jobs(wd, *TARGETS, *cfg) == {}
    before = {t: _md5(wd / t) for t in TARGETS}

    # A comment and a docstring in the code every trainer depends on: nothing reruns.
    fog = wd / "omnilidar" / "domains" / "effects" / "fog.py"
    classes = wd / "omnilidar" / "data" / "synthetic" / "classes.py"
    for f in (fog, classes):
        _edit(f, '"""', '"""Edited docstring. ')
        f.write_text(f.read_text().replace("\n\n", "\n\n# an edited comment\n", 1))
    assert planned_jobs(wd, *TARGETS, *cfg) == {}

    # A fog constant: the Fog domain changes, the generator retrains from scratch.
    _edit(fog, "TAU_H = 20e-9", "TAU_H = 23e-9")
    jobs = planned_jobs(wd, *TARGETS, *cfg)
    assert jobs.get("train_generator") == 1 and "train_labeler" not in jobs, jobs
    snakemake(wd, *TARGETS, *cfg)
    log = (wd / LOGS[GENERATOR]).read_text()
    assert "starting fresh in work/generator/full" in log and "input contents changed: domains" in log
    assert _md5(wd / GENERATOR) != before[GENERATOR]
    assert _md5(wd / LABELER) == before[LABELER] and _md5(wd / SEGMENTOR) == before[SEGMENTOR]

    # A constant of the synthetic world (tyre and lane-marking remission): every scan
    # source changes, so the labeler and the segmentor retrain from scratch too.
    before = {t: _md5(wd / t) for t in TARGETS}
    _edit(classes, "TYRE_REFLECTIVITY = (0.01, 0.04)", "TYRE_REFLECTIVITY = (0.2, 0.3)")
    _edit(classes, "LANE_MARKING_REFLECTIVITY = (0.55, 0.75)", "LANE_MARKING_REFLECTIVITY = (0.9, 0.95)")
    snakemake(wd, *TARGETS, *cfg)
    for target in TARGETS:
        log = (wd / LOGS[target]).read_text()
        assert "starting fresh" in log and "input contents changed" in log, (target, log[-2000:])
        assert _md5(wd / target) != before[target], f"{target}: the same weights after its data changed"


@pytest.mark.slow
def test_more_iterations_resume_in_a_copied_tree_that_reads_only_itself(finished, tmp_path):
    wd, _ = finished
    copy = tmp_path / "copy"
    shutil.copytree(wd, copy, symlinks=True)
    hidden = wd.with_name(wd.name + "_hidden")
    wd.rename(hidden)  # nothing outside the copy can be read while it runs
    try:
        cfg = _config(copy, generator_iterations=4, seg_iterations=4)
        jobs = planned_jobs(copy, *TARGETS, *cfg)
        assert {"train_generator", "train_labeler", "train_supervised"} <= set(jobs), jobs
        snakemake(copy, *TARGETS, *cfg)
    finally:
        hidden.rename(wd)
    for target in TARGETS:
        log = (copy / LOGS[target]).read_text()
        assert "resuming at iteration 3 from iter_3.pth" in log and "provenance matches" in log, (target, log[-2000:])
        assert str(wd) not in log and str(hidden) not in log
        assert (copy / "work" / ("generator/full" if target == GENERATOR else
                                 "labeler" if target == LABELER else SEGMENTOR[:-3]) / "iter_4.pth").is_file()
