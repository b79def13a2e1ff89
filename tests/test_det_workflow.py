"""The detection GDA stage in the workflow: DAG shape of the Pi3DET targets, what reruns
when a detection setting changes (dry runs after a fake completed run), and a real tiny
run of the chain through the commands."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import yaml

from workflow_helpers import (ROOT, copy_workflow, plan_with_change, planned_jobs, run_with_fake_cli, snakemake,
                              synthesized_shards)

TARGET = "results/pi3det_quadruped_1pct.json"
TEST_CONFIG = ROOT / "config" / "test.yaml"


def with_detector_configs(workdir):
    """The detector yamls are inputs of the runs; the dry runs only need them to exist."""
    for name, model in (("voxel_rcnn", "VoxelRCNN"), ("pv_rcnn", "PVRCNN")):
        path = workdir / "config" / "detectors" / f"{name}.yaml"
        if not path.exists():  # stand-in until the detector branches land in this checkout
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(f"MODEL:\n  NAME: {model}\n")
    return workdir


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return with_detector_configs(copy_workflow(tmp_path_factory.mktemp("wf_det")))


def test_headline_dag(workdir):
    jobs = planned_jobs(workdir, TARGET)
    assert jobs["train_box_labeler"] == 1
    assert jobs["train_detector_real"] == 2 and jobs["train_detector_gda"] == 2  # Voxel R-CNN, PV-RCNN
    assert jobs["evaluate_detector"] == 5  # four runs and the labeler
    assert jobs["pseudo_box"] == jobs["sample_domain"] >= 1 and jobs["pi3det_result"] == 1
    # Only Pi3DET is scored; the segmentation stage plans nothing.
    assert not {"train_supervised", "train_labeler", "pseudo_label"} & set(jobs)


def test_every_detection_target_plans(workdir):
    jobs = planned_jobs(workdir, "detection")
    assert jobs["pi3det_result"] == 12
    assert jobs["train_detector_gda"] == 2 * 6 * 2
    # The labeler trains longer than the runs by default (480 against 120 iterations), so the
    # supervised-only Voxel R-CNN at 100 % is a training of its own.
    assert jobs["train_detector_real"] == 2 * 6 * 2
    assert jobs["train_box_labeler"] == 2  # one per platform, shared by its six targets
    assert jobs["evaluate_detector"] == 2 * 6 * 4 + 2


def test_the_labeler_trains_longer_than_the_runs_by_default():
    from omnilidar.config import section_defaults

    det = section_defaults("detection")
    assert det["labeler"]["schedule"]["iterations"] == 4 * det["schedule"]["iterations"]
    # Every other key of the labeler's schedule is the runs' default.
    assert {k: v for k, v in det["labeler"]["schedule"].items() if k != "iterations"} == \
        {k: v for k, v in det["schedule"].items() if k != "iterations"}


def test_labeler_stands_in_for_the_full_supervised_run_only_when_identical(workdir):
    target = "results/pi3det_drone_100pct.json"
    # Labeler and runs on one schedule: the labeler's checkpoint is the supervised-only run.
    same = {"schedule": {"iterations": 120}, "labeler": {"schedule": {"iterations": 120}}}
    base = workdir / "labeler_same.yaml"
    base.write_text(yaml.safe_dump({"downstream": {"det": same}}))
    shared = planned_jobs(workdir, target, "--configfile", str(base))
    assert shared["train_detector_real"] == 1 and shared["evaluate_detector"] == 4  # PV-RCNN's; the labeler's
    for i, change in enumerate(({"schedule": {"iterations": 151}}, {"labeler": {"schedule": {"lr": 0.02}}},
                                {"augmentation": {"flip_x": False}}, {"labeler": {"detector": "pv_rcnn"}})):
        cfg = workdir / f"labeler_change_{i}.yaml"
        cfg.write_text(yaml.safe_dump({"downstream": {"det": change}}))
        out = snakemake(workdir, "--dry-run", target, "--configfile", str(base), str(cfg)).stdout
        assert "data/detection/drone/voxel_rcnn_100pct_real.pt" in out, change
    assert "voxel_rcnn_100pct_real.pt" not in snakemake(workdir, "--dry-run", target, "--configfile", str(base)).stdout
    # The defaults differ (480 against 120 iterations): the run trains.
    assert "voxel_rcnn_100pct_real.pt" in snakemake(workdir, "--dry-run", target).stdout


def test_supervised_runs_and_labeler_take_no_generator_input(workdir):
    jobs = planned_jobs(workdir, "data/detection/drone/voxel_rcnn_5pct_real.pt", "data/detection/drone/labeler.pt")
    assert "sample_domain" not in jobs and "train_generator" not in jobs and "build_domain" not in jobs
    assert jobs == {"synthesize": 3, "index_dataset": 1, "train_detector_real": 1, "train_box_labeler": 1}
    assert set(synthesized_shards(workdir, "data/detection/drone/labeler.pt")) == {"pi3det"}


def test_importing_a_box_labeler_uses_the_checkpoint(workdir):
    (workdir / "user_pvrcnn.pth").write_bytes(b"")
    out = snakemake(workdir, "--dry-run", "data/detection/quadruped/labeler.pt", "--config",
                    'downstream={"det": {"labeler": {"checkpoint": {"quadruped": "user_pvrcnn.pth"}}}}').stdout
    assert "input: user_pvrcnn.pth" in out and "index_dataset" not in out


@pytest.fixture(scope="module")
def completed(tmp_path_factory):
    """The detection target and the segmentation headline run with a fake CLI, so the next
    dry run shows only what a config change reruns."""
    wd = with_detector_configs(copy_workflow(tmp_path_factory.mktemp("wf_det_rerun")))
    cfg = wd / "rerun.yaml"
    cfg.write_text(yaml.safe_dump({"seed": 0}))
    run_with_fake_cli(wd, tmp_path_factory.mktemp("fakebin"), TARGET, "results/semkitti_1pct.json",
                      "--configfile", str(cfg))
    return wd, cfg


def _with_change(wd, cfg, change: dict, *targets):
    return plan_with_change(wd, cfg, change, *(targets or (TARGET, "results/semkitti_1pct.json")))


def test_nothing_reruns_without_a_change(completed):
    wd, cfg = completed
    assert _with_change(wd, cfg, {}) == {}


def test_schedule_change_reruns_only_detector_runs_and_their_evaluations(completed):
    wd, cfg = completed
    jobs = _with_change(wd, cfg, {"downstream.det.schedule.iterations": 41})
    assert jobs == {"train_detector_real": 2, "train_detector_gda": 2, "evaluate_detector": 4, "pi3det_result": 1}


def test_one_detectors_change_reruns_only_its_runs(completed):
    wd, cfg = completed
    jobs = _with_change(wd, cfg, {"downstream.det.detectors.pv_rcnn.overrides": {"PFE": {"NUM_KEYPOINTS": 64}}})
    assert jobs == {"train_detector_real": 1, "train_detector_gda": 1, "evaluate_detector": 2, "pi3det_result": 1}


def test_mixing_change_reruns_only_gda_runs(completed):
    wd, cfg = completed
    jobs = _with_change(wd, cfg, {"downstream.det.mixing.mode": "ratio"})
    assert jobs == {"train_detector_gda": 2, "evaluate_detector": 2, "pi3det_result": 1}


def test_labeler_change_reruns_labeler_pseudo_boxes_and_gda_runs(completed):
    wd, cfg = completed
    jobs = _with_change(wd, cfg, {"downstream.det.labeler.score_threshold": 0.5})
    assert {"train_box_labeler", "pseudo_box", "train_detector_gda", "pi3det_result"} <= set(jobs)
    assert "train_detector_real" not in jobs and "sample_domain" not in jobs and "train_labeler" not in jobs
    assert jobs["evaluate_detector"] == 3  # the labeler's and the two GDA runs'


def test_evaluation_change_reruns_only_evaluations(completed):
    wd, cfg = completed
    jobs = _with_change(wd, cfg, {"downstream.det.evaluation.batch_size": 3})
    assert jobs == {"evaluate_detector": 5, "pi3det_result": 1}


def test_segmentation_change_spares_detection_and_back(completed):
    wd, cfg = completed
    jobs = _with_change(wd, cfg, {"downstream.schedule.iterations": 41})
    assert not {"train_detector_real", "train_detector_gda", "evaluate_detector", "pi3det_result"} & set(jobs)
    jobs = _with_change(wd, cfg, {"downstream.det.voxel_size": [0.4, 0.4, 0.15]})
    assert not {"train_supervised", "train_gda", "evaluate_segmentor", "semkitti_result"} & set(jobs)


# --------------------------------------------------------------------------- a real tiny run of the chain

def _omnilidar(*args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-m", "omnilidar.cli", *map(str, args)], cwd=cwd, env=env,
                         capture_output=True, text=True)
    assert out.returncode == 0, f"omnilidar {args[0]} failed:\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    return out.stdout


@pytest.fixture(scope="module")
def tiny_chain(tmp_path_factory):
    """Labeler, pseudo-boxes, supervised-only and GDA Voxel R-CNN for real on a tiny synthetic Drone set
    (the generated scans are the platform's val scans copied into a sample shard)."""
    import json
    import shutil

    from omnilidar.config import validate

    tmp_path = tmp_path_factory.mktemp("det_chain")
    test_cfg = yaml.safe_load(TEST_CONFIG.read_text())
    synthetic = validate(test_cfg.get("synthetic", {}), "synthetic.schema.yaml")
    root = tmp_path / "pi3det"
    _omnilidar("synthesize", "pi3det", "--shard", "drone", "--settings", json.dumps(synthetic), "--seed", 0,
               "--out", root / "drone", cwd=tmp_path)
    _omnilidar("index-dataset", "pi3det", "--root", root, "--source", "synthetic", "--out", tmp_path / "index.json",
               cwd=tmp_path)
    settings = json.dumps(test_cfg["downstream"]["det"])
    model = ROOT / "config" / "detectors" / "voxel_rcnn.yaml"
    _omnilidar("train-box-labeler", "--platform", "drone", "--index", tmp_path / "index.json", "--model-config", model,
               "--settings", settings, "--work-dir", tmp_path / "work/labeler", "--out", tmp_path / "labeler.pt",
               cwd=tmp_path)
    shard = tmp_path / "samples" / "Drone" / "shard_0"
    (shard / "velodyne").mkdir(parents=True)
    for scan in sorted((root / "drone" / "velodyne").glob("*.bin"))[-2:]:
        shutil.copy(scan, shard / "velodyne" / scan.name)
    _omnilidar("pseudo-box", "--labeler", tmp_path / "labeler.pt", "--samples", shard, "--settings", settings,
               "--out", tmp_path / "pseudo" / "shard_0", cwd=tmp_path)
    for role, extra in (("real", []), ("gda", ["--samples", shard, "--pseudo-boxes", tmp_path / "pseudo" / "shard_0"])):
        _omnilidar("train-detector", "--detector", "voxel_rcnn", "--platform", "drone", "--index",
                   tmp_path / "index.json", "--percent", 100, "--model-config", model, "--settings", settings,
                   "--work-dir", tmp_path / "work" / role, "--out", tmp_path / f"voxel_rcnn_100pct_{role}.pt", *extra,
                   cwd=tmp_path)
    return tmp_path, root, settings, shard


@pytest.mark.slow
def test_tiny_chain_trains_for_real(tiny_chain):
    import torch

    from omnilidar.downstream.det.checkpoints import load_payload
    from omnilidar.io import pi3det

    tmp_path, _, _, shard = tiny_chain
    labeler = load_payload(tmp_path / "labeler.pt")
    assert labeler["train"]["info"]["role"] == "labeler" and labeler["data"]["class_names"] == ["Car"]
    infos = pi3det.read_infos(tmp_path / "pseudo" / "shard_0" / "infos.pkl")
    assert [i["frame_id"] for i in infos] == sorted(p.stem for p in (shard / "velodyne").glob("*.bin"))
    real, gda = (load_payload(tmp_path / f"voxel_rcnn_100pct_{r}.pt") for r in ("real", "gda"))
    assert real["train"]["num_generated"] == 0 and gda["train"]["num_generated"] == 2
    assert real["iterations"] == gda["iterations"] == 2
    assert all(torch.isfinite(v).all() for v in real["model_state"].values() if v.is_floating_point())
    # OpenPCDet's checkpoint key and names: the weights load strictly into a freshly built detector.
    from omnilidar.downstream.det.runs import load_detector

    net, cfg, _ = load_detector(tmp_path / "voxel_rcnn_100pct_gda.pt", "cpu")
    assert cfg.platform == "drone" and any(k.startswith("roi_head.") for k in real["model_state"])


@pytest.mark.slow
def test_tiny_chain_scores_for_real(tiny_chain):
    """Evaluation of the runs and the labeler, and the result target."""
    import json

    pytest.importorskip("omnilidar.metrics.kitti_ap", reason="KITTI evaluator (det-eval) not merged yet")
    tmp_path, root, settings, shard = tiny_chain
    evaluations = []
    for role in ("real", "gda"):
        evaluations.append(tmp_path / f"{role}.val.json")
        _omnilidar("evaluate-detector", "--checkpoint", tmp_path / f"voxel_rcnn_100pct_{role}.pt", "--index",
                   tmp_path / "index.json", "--settings", settings, "--out", evaluations[-1], cwd=tmp_path)
    _omnilidar("evaluate-detector", "--checkpoint", tmp_path / "labeler.pt", "--index", tmp_path / "index.json",
               "--settings", settings, "--out", tmp_path / "labeler.val.json", cwd=tmp_path)
    source = json.dumps({"pi3det": {"root": str(root), "kind": "synthetic"}})
    _omnilidar("pi3det-result", "--experiment", "pi3det_drone_100pct", "--platform", "drone", "--percent", 100,
               "--settings", settings, "--data-source", source, "--evaluations", *evaluations,
               "--labeler-evaluation", tmp_path / "labeler.val.json", "--pseudo-boxes", tmp_path / "pseudo" / "shard_0",
               "--out", tmp_path / "result.json", "--figure", tmp_path / "result.png", cwd=tmp_path)
    doc = json.loads((tmp_path / "result.json").read_text())
    run = doc["runs"]["voxel_rcnn"]
    assert doc["experiment"] == "pi3det_drone_100pct" and doc["classes"] == ["Car"]
    assert run["supervised_only"]["train_frames"]["generated"] == 0 and run["gda"]["train_frames"]["generated"] == 2
    for role in ("supervised_only", "gda"):
        ap = run[role]["ap"]["Car"]
        assert 0.0 <= ap["3d_R11@0.5"] <= 100.0 and 0.0 <= ap["3d_R40@0.5"] <= 100.0 and ap["gt_boxes"] > 0
        assert {"roi_0.3", "rcnn_0.7"} <= set(run[role]["recall"])
    assert doc["labeler"]["generated_scans"] == 2 and "Car" in doc["labeler"]["val_ap"]
    assert {"labeler_train", "pseudo_boxes", "train_voxel_rcnn_gda"} <= set(doc["timings"])
    assert (tmp_path / "result.png").stat().st_size > 10_000
