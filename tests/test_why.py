"""omnilidar why: the dry run's reasons in words (settings keys, code files, inputs)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import yaml

from omnilidar.rerun_reasons import params_changes, reason_in_words, settings_changes
from workflow_helpers import copy_workflow, embedded_default, run_with_fake_cli

TARGET = "results/semkitti_1pct.json"


def test_settings_and_code_hashes_are_told_apart_and_diffed(tmp_path):
    assert settings_changes({"a": {"b": 1, "c": 2}}, {"a": {"b": 1, "c": 3}, "d": True}) == [
        "setting a.c: 2 -> 3", "setting d: (absent) -> true"]
    (tmp_path / ".snakemake" / "omnilidar" / "code").mkdir(parents=True)
    for digest, files in {"aaaaaaaaaaaaaaaa": {"x.py": "1", "y.py": "2"}, "bbbbbbbbbbbbbbbb": {"x.py": "1", "y.py": "3"}}.items():
        (tmp_path / ".snakemake" / "omnilidar" / "code" / f"{digest}.json").write_text(json.dumps(files))
    changes = params_changes(['{"lr": 0.1}', 'aaaaaaaaaaaaaaaa {"torch": "2.1"}'],
                             ['bbbbbbbbbbbbbbbb {"torch": "2.2"}', '{"lr": 0.2}'], tmp_path)
    assert changes == ["setting lr: 0.1 -> 0.2", "code y.py changed", "package torch: 2.1 -> 2.2"]
    reason = ("Params have changed since last execution: Union of exclusive params before and now across all output: "
              "before: 'cccccccccccccccc' now: 'bbbbbbbbbbbbbbbb'")
    assert reason_in_words(reason, tmp_path) == [
        "code cccccccccccccccc -> bbbbbbbbbbbbbbbb (no record of the files behind the old hash)"]
    assert reason_in_words("Missing output files: a.pt", tmp_path) == ["Missing output files: a.pt"]


def test_why_names_the_changed_setting_and_code_file_of_each_job(tmp_path):
    (tmp_path / "wf").mkdir()
    wd = copy_workflow(tmp_path / "wf")
    run_with_fake_cli(wd, tmp_path / "bin", TARGET, "--configfile", "config/test.yaml")
    cfg = yaml.safe_load((wd / "config" / "test.yaml").read_text())
    configured = embedded_default(wd)["downstream"]["schedule"]["iterations"]
    cfg["downstream"]["schedule"] = {"iterations": 3}  # config.yaml's otherwise
    (wd / "changed.yaml").write_text(yaml.safe_dump(cfg))
    fog = wd / "omnilidar" / "domains" / "effects" / "fog.py"
    fog.write_text(fog.read_text() + "\n_EDITED = True\n")

    env = dict(os.environ, PYTHONPATH=str(wd), PYTHONDONTWRITEBYTECODE="1")
    out = subprocess.run([sys.executable, "-m", "omnilidar.cli", "why", TARGET, "--configfile", "changed.yaml"],
                         cwd=wd, env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    text = out.stdout
    blocks = {line.split(" -> ")[1]: [] for line in text.splitlines() if not line.startswith(" ") and " -> " in line}
    current = None
    for line in text.splitlines():
        if not line.startswith(" ") and " -> " in line:
            current = line.split(" -> ")[1]
        elif line.startswith("    ") and current:
            blocks[current].append(line.strip())
    train = next(v for k, v in blocks.items() if k.endswith("minkunet_1pct_real.pt"))
    assert f"setting schedule.iterations: {configured} -> 3" in train, text
    fog_build = next(v for k, v in blocks.items() if k.startswith("data/domains/fog/"))
    assert "code omnilidar/domains/effects/fog.py changed" in fog_build, text
    vehicle = [v for k, v in blocks.items() if k.startswith("data/domains/vehicle/")]
    assert not vehicle, "a domain without fog does not rebuild"
