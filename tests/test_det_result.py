"""pi3det-result: assembling a Pi3DET target from evaluate-detector outputs (JSON + figure)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from workflow_helpers import ROOT


def evaluation(detector: str, role: str, ap: float, classes=("Car", "Pedestrian")) -> dict:
    curve = list(np.linspace(1.0, 0.0, 41).clip(0, 1) * ap / 100)
    return {"checkpoint": f"{detector}_{role}.pt", "detector": detector, "platform": "quadruped",
            "split": "quadruped_val", "frames": 30, "classes": list(classes),
            "ap": {c: {"3d_R11@0.5": ap, "3d_R40@0.5": ap - 1, "bev_R11@0.5": ap + 1, "bev_R40@0.5": ap,
                       "precision_3d@0.5": curve, "gt_boxes": 40, "detections": 80} for c in classes},
            "recall": {"roi_0.3": 0.5, "rcnn_0.3": 0.6, "rcnn_0.7": 0.1, "gt": 40},
            "train": {"seconds": 12.0, "iterations": 30, "num_real": 1, "num_generated": 0 if role != "gda" else 16,
                      "mixing": {"mode": "concat"}, "info": {"role": role}},
            "timings": {"train_seconds": 12.0, "inference_seconds_per_frame": 0.2, "evaluate_seconds": 7.0}}


def test_result_compares_runs_and_records_the_labeler(tmp_path):
    paths = []
    for det, sup, gda in (("voxel_rcnn", 0.5, 20.0), ("pv_rcnn", 1.0, 3.0)):
        for role, ap in (("supervised_only", sup), ("gda", gda)):
            p = tmp_path / f"{det}_{role}.json"
            p.write_text(json.dumps(evaluation(det, role, ap)))
            paths.append(p)
    labeler = tmp_path / "labeler.json"
    labeler.write_text(json.dumps(evaluation("voxel_rcnn", "labeler", 55.0)))
    shard = tmp_path / "pseudo" / "shard_0"
    shard.mkdir(parents=True)
    (shard / "sidecar.json").write_text(json.dumps({"scans": 16, "boxes": {"Car": 30, "Pedestrian": 4},
                                                    "score_threshold": 0.3, "seconds": 4.5}))
    cmd = [sys.executable, "-m", "omnilidar.cli", "pi3det-result", "--experiment", "pi3det_quadruped_1pct",
           "--platform", "quadruped", "--percent", "1", "--settings", "{}", "--data-source",
           json.dumps({"pi3det": {"root": "data/synthetic/pi3det", "kind": "synthetic"}}),
           "--evaluations", *map(str, paths), "--labeler-evaluation", str(labeler), "--pseudo-boxes", str(shard),
           "--out", str(tmp_path / "r.json"), "--figure", str(tmp_path / "r.png")]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
    doc = json.loads((tmp_path / "r.json").read_text())
    assert {"experiment", "config_hash", "code_hash", "data_source", "device", "seeds", "timings"} <= set(doc)
    vx = doc["runs"]["voxel_rcnn"]
    assert vx["gda_gain"]["Car"]["3d_R11@0.5"] == 19.5 and vx["gda"]["train_frames"]["generated"] == 16
    assert vx["paper_3d_R11@0.5"]["Pedestrian"] == {"supervised_only": 0.91, "gda": 33.05}
    assert doc["runs"]["pv_rcnn"]["paper_3d_R11@0.5"] is None
    assert "precision_3d@0.5" not in vx["gda"]["ap"]["Car"]  # curves go to the figure only
    assert doc["labeler"]["val_ap"]["Car"]["3d_R11@0.5"] == 55.0 and doc["labeler"]["pseudo_boxes"]["Car"] == 30
    assert doc["timings"]["pseudo_boxes"] == 4.5 and doc["timings"]["train_pv_rcnn_gda"] == 12.0
    assert (tmp_path / "r.png").stat().st_size > 10_000
    # The box labeler (55 AP) is above both supervised-only detectors: no warning.
    check = doc["labeler_check"]
    assert check["warning"] is None and check["students"]["pv_rcnn"]["Car"] == {
        "student_ap": 1.0, "labeler_ap": 55.0, "labeler_stronger": True}
    assert "WARNING" not in res.stderr
    # A labeler below a student it labels for: said in the JSON and on the terminal.
    labeler.write_text(json.dumps(evaluation("voxel_rcnn", "labeler", 0.8)))
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
    check = json.loads((tmp_path / "r.json").read_text())["labeler_check"]
    assert check["students"]["pv_rcnn"]["Car"]["labeler_stronger"] is False
    assert check["students"]["voxel_rcnn"]["Car"]["labeler_stronger"] is True  # 0.8 > 0.5
    assert "pv_rcnn Car (1.00 against the labeler's 0.80)" in check["warning"]
    assert "WARNING: the box labeler's val 3d_R11@0.5 is not above" in res.stderr


def test_result_needs_both_runs_of_each_detector(tmp_path):
    p = tmp_path / "only.json"
    p.write_text(json.dumps(evaluation("voxel_rcnn", "gda", 3.0)))
    cmd = [sys.executable, "-m", "omnilidar.cli", "pi3det-result", "--experiment", "x", "--platform", "quadruped",
           "--percent", "1", "--data-source", json.dumps({"pi3det": {"root": "r", "kind": "synthetic"}}), "--evaluations", str(p), "--labeler-evaluation", str(p),
           "--out", str(tmp_path / "r.json"), "--figure", str(tmp_path / "r.png")]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 2 and "no supervised_only evaluation" in res.stderr
    assert not (tmp_path / "r.json").exists()


def test_the_labeler_stands_in_for_the_supervised_only_run_at_100_percent(tmp_path):
    """At 100 % with the labeler's own detector and schedule the workflow passes the labeler's
    evaluation as the supervised-only run (the same training); it is marked as such."""
    labeler = evaluation("voxel_rcnn", "labeler", 31.0, classes=("Car",))
    labeler["train"]["info"]["percent"] = 100.0
    paths = {"labeler": labeler, "gda": evaluation("voxel_rcnn", "gda", 30.0, classes=("Car",))}
    for name, doc in paths.items():
        (tmp_path / f"{name}.json").write_text(json.dumps(doc))
    cmd = [sys.executable, "-m", "omnilidar.cli", "pi3det-result", "--experiment", "pi3det_drone_100pct",
           "--platform", "drone", "--percent", "100", "--settings", "{}", "--data-source",
           json.dumps({"pi3det": {"root": "r", "kind": "synthetic"}}),
           "--evaluations", str(tmp_path / "labeler.json"), str(tmp_path / "gda.json"),
           "--labeler-evaluation", str(tmp_path / "labeler.json"),
           "--out", str(tmp_path / "r.json"), "--figure", str(tmp_path / "r.png")]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
    vx = json.loads((tmp_path / "r.json").read_text())["runs"]["voxel_rcnn"]
    assert vx["supervised_only"]["is_labeler"] and not vx["gda"]["is_labeler"]
    assert vx["gda_gain"]["Car"]["3d_R11@0.5"] == -1.0
    # A labeler trained on a subset (or imported) is not a supervised-only run.
    labeler["train"]["info"]["percent"] = 50.0
    (tmp_path / "labeler.json").write_text(json.dumps(labeler))
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 2 and "no supervised_only evaluation" in res.stderr


def test_summary_draws_car_ap_against_the_label_fraction(tmp_path):
    paths = []
    for platform in ("drone", "quadruped"):
        for pct, sup, gda in ((1, 0.5, 2.0), (100, 30.0, 28.0)):
            frames = max(1, 40 * pct // 100)
            runs = {det: {role: {"ap": {"Car": {"3d_R11@0.5": ap, "3d_R40@0.5": ap / 2}}, "iterations": 120,
                                 "train_frames": {"real": frames, "generated": 16 if role == "gda" else 0},
                                 "is_labeler": False}
                          for role, ap in (("supervised_only", sup), ("gda", gda))}
                    for det in ("voxel_rcnn", "pv_rcnn")}
            doc = {"platform": platform, "label_percent": pct, "runs": runs, "config_hash": f"c{pct}",
                   "labeler": {"val_ap": {"Car": {"3d_R11@0.5": 31.0, "3d_R40@0.5": 28.0}},
                               "pseudo_boxes": {"Car": 8}, "generated_scans": 16},
                   "labeler_check": {"warning": None}}
            paths.append(tmp_path / f"pi3det_{platform}_{pct}pct.json")
            paths[-1].write_text(json.dumps(doc))
    figure, table = tmp_path / "fractions.png", tmp_path / "summary.json"
    cmd = [sys.executable, "-m", "omnilidar.cli", "pi3det-summary", *map(str, paths), "--out", str(table),
           "--figure", str(figure)]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "drone 100 %: pv_rcnn 30.00 -> 28.00, voxel_rcnn 30.00 -> 28.00" in res.stdout
    assert figure.stat().st_size > 20_000
    # One row per target in platform and label order, each naming its source file.
    rows = json.loads(table.read_text())["targets"]
    assert [(r["platform"], r["label_percent"]) for r in rows] == [("drone", 1), ("drone", 100),
                                                                   ("quadruped", 1), ("quadruped", 100)]
    assert rows[1]["runs"]["pv_rcnn"]["gda"]["Car"] == {"3d_R11@0.5": 28.0, "3d_R40@0.5": 14.0}
    assert rows[1]["runs"]["pv_rcnn"]["real_frames"] == 40 and rows[1]["source"]["file"] == str(paths[1])
    assert rows[0]["labeler"]["pseudo_boxes"] == {"Car": 8}
    # docs/detection.md's block renders from it: one line per target.
    from omnilidar.report.readme import pi3det_summary

    text = pi3det_summary(json.loads(table.read_text()))
    assert "| drone | 100 | 40 | 30.00 (15.00) -> 28.00 (14.00) | 30.00 (15.00) -> 28.00 (14.00) | 31.00 (28.00) | 8 on 16 |" in text
    assert "above every supervised-only detector" in text
    assert "GDA raises Car R11 in 4 of the 8 comparisons, lowers it in 4, ties in 0." in text
    paths[0].write_text(json.dumps({"ap": {}}))
    table.unlink()
    res = subprocess.run(cmd[:-1] + [str(tmp_path / "bad.png")], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 2 and "not a pi3det-result output" in res.stderr and str(paths[0]) in res.stderr
    assert not (tmp_path / "bad.png").exists() and not table.exists()
