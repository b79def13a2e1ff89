"""Downstream trainings cut into segment jobs (a partition's time limit: `--segment K/N`) end with
the weights of one uninterrupted run, bit for bit on CPU: the segments split the run's own
iteration count, and each resumes its predecessor's state with the random streams (dropout,
RoI and anchor sampling) where the predecessor left them."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from omnilidar.checkpoints import parse_segment, segment_until
from omnilidar.cli import main
from omnilidar.config import validate
from omnilidar.data.index import build_index, write_index
from omnilidar.downstream.seg.dataset import records_from_entries
from omnilidar.downstream.seg.label_spaces import get_label_space
from omnilidar.downstream.seg.training import train_segmentor
from omnilidar.errors import InputError
from test_downstream_training import _settings, _write_sequence

SPACE = get_label_space("semantickitti")


def test_segments_split_the_runs_own_iterations():
    assert [segment_until((k, 3), 10) for k in (1, 2)] == [3, 6]
    assert segment_until(None, 10) is None
    assert segment_until((1, 4), 2) == 1  # never before the first step
    assert parse_segment("2/5") == (2, 5)
    for bad in ((0, 3), (3, 3), (4, 3)):
        with pytest.raises(InputError, match="the last part is the job itself"):
            segment_until(bad, 10)
    with pytest.raises(InputError, match="expected K/N"):
        parse_segment("half")


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    root = tmp_path_factory.mktemp("segscans")
    return records_from_entries(_write_sequence(root / "train", 3, 0), "semantickitti")


def _weights(path, key="state_dict"):
    return torch.load(path, map_location="cpu", weights_only=True)[key]


def _chain(settings, scans, tmp_path, work):
    for k in (1, 2):
        part = train_segmentor(settings, "spvcnn", scans, [], SPACE, tmp_path / f"part{k}.json", tmp_path / work,
                               seed=3, segment=(k, 3))
        record = json.loads((tmp_path / f"part{k}.json").read_text())
        assert record["segment"] == f"{k}/3" and record["segment_until"] == part["iterations"] == [1, 3][k - 1]
    return train_segmentor(settings, "spvcnn", scans, [], SPACE, tmp_path / f"{work}.pt", tmp_path / work, seed=3)


def test_a_segmentor_chain_ends_with_the_uninterrupted_weights(scans, tmp_path, monkeypatch):
    """SPVCNN: its seeded dropout draws from generators the chain must carry across jobs."""
    settings = _settings(iterations=5)
    whole = train_segmentor(settings, "spvcnn", scans, [], SPACE, tmp_path / "whole.pt", tmp_path / "w1", seed=3)
    last = _chain(settings, scans, tmp_path, "chain")
    assert whole["iterations"] == last["iterations"] == 5 and last["resumed_from"] == 3
    a, b = _weights(tmp_path / "whole.pt"), _weights(tmp_path / "chain.pt")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    # Without the random streams put back, the dropout masks restart from the seed: other weights.
    monkeypatch.setattr("omnilidar.checkpoints.load_random_states", lambda net, states: None)
    _chain(settings, scans, tmp_path, "forgetful")
    c = _weights(tmp_path / "forgetful.pt")
    assert any(not torch.equal(a[k], c[k]) for k in a)


def _platform(root):
    from omnilidar.data.synthetic.export import write_shard

    settings = validate({"datasets": {"pi3det": {"platforms": {"drone": {"scenes": 1, "scans_per_scene": 3}}}}},
                        "synthetic.schema.yaml")
    write_shard("pi3det", "drone", settings, 0, root / "drone")
    write_index(build_index("pi3det", root), root / "index.json")
    return root / "index.json"


def test_a_detector_chain_through_the_cli_ends_with_the_uninterrupted_weights(tmp_path):
    """Voxel R-CNN: dropout in the RoI head (torch's global generator) and seeded RoI / anchor sampling."""
    index = _platform(tmp_path)
    settings = json.dumps({"schedule": {"iterations": 4, "batch_size": 2, "checkpoint_interval": 2, "log_interval": 1}})
    common = ["train-detector", "--detector", "voxel_rcnn", "--platform", "drone", "--index", str(index),
              "--percent", "100", "--settings", settings, "--seed", "2"]
    assert main([*common, "--work-dir", str(tmp_path / "w1"), "--out", str(tmp_path / "whole.pt")]) == 0
    assert main([*common, "--work-dir", str(tmp_path / "w2"), "--segment", "1/2", "--out", str(tmp_path / "part.json")]) == 0
    assert json.loads((tmp_path / "part.json").read_text())["segment_until"] == 2
    assert main([*common, "--work-dir", str(tmp_path / "w2"), "--out", str(tmp_path / "chain.pt")]) == 0
    a, b = _weights(tmp_path / "whole.pt", "model_state"), _weights(tmp_path / "chain.pt", "model_state")
    assert torch.load(tmp_path / "chain.pt", weights_only=True)["train"]["resumed_from"] == 2
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# --------------------------------------------------------------------------- through the workflow

RUN = "data/segmentation/semantickitti/minkunet_1pct_real.pt"
STUDENT = "downstream: {schedule: {iterations: 5, batch_size: 2, checkpoint_interval: 2, log_interval: 1}}\n"
# 5 iterations x 2 scans x 450 s against a 30-minute partition (no set-up time, no margin): 4,500 s
# in three jobs of 1,500 s: segments up to iterations 1 and 3, then the training's own job.
CHAIN = "gpus: false, setup_min: 0, margin: 1, rates: {segmentor_scan_step_cpu_s: 450}, "


@pytest.mark.slow
def test_a_student_training_longer_than_its_partition_runs_as_a_chain_with_the_same_weights(tmp_path):
    import re

    from workflow_helpers import planned_jobs, snakemake, whole_and_chained

    whole, chained, run, chain = whole_and_chained(tmp_path, STUDENT, RUN, CHAIN,
                                                   ("data/segmentation", "work/data/segmentation"))
    dry = snakemake(chained, "--dry-run", *chain, "--", RUN).stdout
    jobs = re.findall(r"rule (train_supervised\w*):.*?output: (\S+).*?runtime=(\d+)", dry, re.S)
    assert sorted((rule, out) for rule, out, _ in jobs) == [
        ("train_supervised", RUN),
        ("train_supervised_segment", "data/segmentation/semantickitti/segments/minkunet_1pct_real.1of3.json"),
        ("train_supervised_segment", "data/segmentation/semantickitti/segments/minkunet_1pct_real.2of3.json")]
    assert all(int(minutes) == 25 for _, _, minutes in jobs)  # each its share, within the 30 minutes
    snakemake(chained, *chain, "--", RUN)

    a, b = (torch.load(d / RUN, map_location="cpu", weights_only=True) for d in (whole, chained))
    assert a["iterations"] == b["iterations"] == 5 and b["train"]["resumed_from"] == 3
    assert all(torch.equal(a["state_dict"][k], b["state_dict"][k]) for k in a["state_dict"])
    records = [json.loads((chained / f"data/segmentation/semantickitti/segments/minkunet_1pct_real.{k}of3.json")
                          .read_text()) for k in (1, 2)]
    assert [r["segment_until"] for r in records] == [1, 3]
    log = (chained / "logs/downstream/train/semantickitti_minkunet_1pct_real.part2of3.log").read_text()
    assert "resuming at iteration 1" in log
    assert planned_jobs(chained, RUN, *chain) == {}
    # Without the partition limit the training is one job whose inputs lack the chain's records:
    # Snakemake reruns it, and it resumes the finished state instead of training again.
    assert planned_jobs(chained, RUN, *run) == {"train_supervised": 1}
    snakemake(chained, *run, "--", RUN)
    assert "resuming at iteration 5" in (chained / "logs/downstream/train/semantickitti_minkunet_1pct_real.log").read_text()
    c = torch.load(chained / RUN, map_location="cpu", weights_only=True)
    assert all(torch.equal(a["state_dict"][k], c["state_dict"][k]) for k in a["state_dict"])
