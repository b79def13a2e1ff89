"""The workflow report: every result writes an HTML table beside its JSON and figure, and
`snakemake --report report.html` works after any run, gathering what exists."""

from __future__ import annotations

import json

import numpy as np
import yaml

from ground_scenes import make_scene
from omnilidar.io import semantickitti
from omnilidar.lidar.sensors import PRESETS
from omnilidar.report.result_table import result_table_html
from workflow_helpers import copy_workflow, planned_jobs, snakemake

RESULT = {
    "experiment": "semkitti_1pct",
    "config_hash": "abc123",
    "data_source": {"semantickitti": {"root": "/data/skitti", "kind": "real"}},
    "device": "cpu",
    "seeds": [0, 1],
    "runs": {"supervised": {"miou": 0.41234567, "iou": {"car": 0.9, "road": 0.8}},
             "gda": {"miou": 0.5949, "iou": {"car": 0.95, "road": 0.85}}},
    "timings": {"train_s": 12.5, "eval_s": 3.25},
    "notes": [{"step": 1, "loss": 1.5}, {"step": 2, "loss": 1.25}],
}


def test_result_table_holds_the_numbers_and_the_provenance():
    page = result_table_html(RESULT)
    for text in ("semkitti_1pct", "abc123", "/data/skitti", "real", "0.4123", "0.5949", "iou/car", "train_s",
                 "12.5", "1.25"):
        assert text in page, text
    # One row per run, one column per metric: both runs' car IoU sit in one column.
    assert page.count("<th>iou/car</th>") == 1 and page.index("0.9<") < page.index("0.95<")


def test_result_table_command_refuses_bad_input(tmp_path, capsys):
    from omnilidar.cli import main

    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    out = tmp_path / "t.html"
    assert main(["result-table", str(bad), "--out", str(out)]) != 0
    assert "bad.json" in capsys.readouterr().err and not out.exists()


def test_report_after_a_partial_run_holds_the_tables_made_so_far(tmp_path):
    """After one result target (not the default `all`), the bare report command works and
    gathers that result's table and figure; before any run it works too (nothing to gather)."""
    (tmp_path / "wf").mkdir()
    workdir = copy_workflow(tmp_path / "wf")
    assert snakemake(workdir, "--report", "empty.html").returncode == 0
    scans = []
    for i in range(2):
        scans.append(tmp_path / f"{i:06d}.bin")
        scan = make_scene(PRESETS["kitti_hdl64e"], np.random.default_rng(i), azimuth_steps=128)
        semantickitti.write_points(scans[-1], scan.points)
    overlay = tmp_path / "fidelity.yaml"
    overlay.write_text(yaml.safe_dump({"domains": {"fidelity": {
        "scans": [str(p) for p in scans], "effects": ["beam_reduction"], "seeds": [0], "max_scans": 2}}}))
    cfg = ("--configfile", "config/config.yaml", str(overlay))
    snakemake(workdir, "results/domain_fidelity.json", *cfg)
    table = (workdir / "results/tables/domain_fidelity.html").read_text()
    result = json.loads((workdir / "results/domain_fidelity.json").read_text())
    assert result["experiment"] in table or "domain_fidelity" in table
    assert planned_jobs(workdir, "results/domain_fidelity.json", *cfg) == {}

    out = snakemake(workdir, "--report", "report.html", *cfg)
    log = out.stdout + out.stderr
    assert "Adding domain_fidelity.html" in log and "Adding domain_fidelity.png" in log
    assert "Adding data_summary" not in log and "Report created" in log  # never made: not asked for
    assert "Missing metadata" not in log, log  # nothing said of files never made
    assert (workdir / "report.html").stat().st_size > (workdir / "empty.html").stat().st_size
