"""Every result names each dataset it used, real or synthetic, and the workflow warns
once when a run mixes them."""

from __future__ import annotations

import argparse
import json

import pytest

from omnilidar import data_source
from workflow_helpers import copy_workflow, snakemake


def test_parse_checks_every_entry():
    good = {"semantickitti": {"root": "/data/kitti", "kind": "real"},
            "pi3det": {"root": "data/synthetic/pi3det", "kind": "synthetic"}}
    assert data_source.parse(json.dumps(good)) == good
    assert data_source.mixed(good) and not data_source.mixed({"pi3det": good["pi3det"]})
    assert data_source.describe(good) == "real semantickitti (/data/kitti), synthetic pi3det (data/synthetic/pi3det)"
    for bad in ("synthetic", "{}", '{"a": {"root": "x", "kind": "simulated"}}', '{"a": {"root": "x"}}'):
        with pytest.raises(argparse.ArgumentTypeError):
            data_source.parse(bad)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    wd = copy_workflow(tmp_path_factory.mktemp("wf_sources"))
    (wd / "real_kitti").mkdir()
    return wd


def _dry_run(wd, *config):
    out = snakemake(wd, "--dry-run", "--printshellcmds", "results/semkitti_1pct.json", *config)
    return out.stdout + out.stderr


def test_mixed_run_warns_once_and_results_name_each_dataset(workdir):
    text = _dry_run(workdir, "--config", 'datasets={"semantickitti": {"root": "real_kitti"}}')
    warnings = [line for line in text.splitlines() if line.startswith("Warning: results mix real and synthetic")]
    assert len(warnings) == 1
    assert "semkitti_*pct, semkittic, semanticstf, gda_curve use real semantickitti, synthetic pi3det" in warnings[0]
    command = next(line for line in text.splitlines() if "omnilidar gda-result" in line)
    recorded = json.loads(command.split("--data-source '", 1)[1].split("'", 1)[0])
    assert recorded == {"semantickitti": {"root": "real_kitti", "kind": "real"},
                        "pi3det": {"root": "data/synthetic/pi3det", "kind": "synthetic"}}


def test_all_synthetic_run_does_not_warn(workdir):
    text = _dry_run(workdir)
    assert "mix real and synthetic" not in text
    command = next(line for line in text.splitlines() if "omnilidar gda-result" in line)
    assert '"semantickitti": {"kind": "synthetic", "root": "data/synthetic/semantickitti"}' in command
