"""A generator training cut into segment jobs (a partition's time limit) ends with the weights of
one uninterrupted run, bit for bit on CPU; a segment resumes its predecessor's state."""

from __future__ import annotations

import pytest
import torch

from workflow_helpers import planned_jobs, snakemake, whole_and_chained

pytestmark = pytest.mark.slow

MODEL = "data/generator/full/model.pt"
# Five iterations; one costs 12 estimated minutes against a 30-minute partition (no set-up time, no
# margin), so the chain is: iterations 0-2, 2-4, then the final job 4-5.
RUN = "generator: {training: {iterations: 5, checkpoint_interval: 2}}\n"
# Set-up time and margin off, generator steps of 12 minutes.
CHAIN = "gpus: false, setup_min: 0, margin: 1, rates: {train_step_s: 184320}, runtime: {build_domain: 30}, "


def test_segment_chain_equals_an_uninterrupted_generator_training(tmp_path):
    # The same inputs, generator cut into a chain by the tighter partition.
    whole, chained, run, chain = whole_and_chained(tmp_path, RUN, MODEL, CHAIN, ("data/generator", "work/generator"))
    assert {k: v for k, v in planned_jobs(chained, MODEL, *chain).items() if k.startswith("train")} == \
        {"train_generator_segment": 2, "train_generator": 1}
    snakemake(chained, *chain, "--", MODEL)

    a, b = (torch.load(d / MODEL, map_location="cpu", weights_only=False) for d in (whole, chained))
    assert a["iterations"] == b["iterations"] == 5 and a["resumed_from"] == 0 and b["resumed_from"] == 4
    assert a["state_dict"].keys() == b["state_dict"].keys()
    assert all(torch.equal(a["state_dict"][k], b["state_dict"][k]) for k in a["state_dict"])
    segments = sorted(p.name for p in (chained / "data/generator/full/segments").iterdir())
    assert segments == ["until_2.json", "until_4.json"]
    assert "resuming at iteration 2" in (chained / "logs/generator/train_full_until_4.log").read_text()
    assert planned_jobs(chained, MODEL, *chain) == {}

    # A setting that changes what a step computes reruns the whole chain from scratch (the work
    # directory's state belongs to the old settings) and changes the weights.
    (tmp_path / "run.yaml").write_text(RUN.replace("checkpoint_interval: 2", "checkpoint_interval: 2, lr: 0.001"))
    assert {k: v for k, v in planned_jobs(chained, MODEL, *chain).items() if k.startswith("train")} == \
        {"train_generator_segment": 2, "train_generator": 1}
    snakemake(chained, *chain, "--", MODEL)
    first_segment = (chained / "logs/generator/train_full_until_2.log").read_text()
    assert "from scratch" in first_segment and "resuming at" not in first_segment
    c = torch.load(chained / MODEL, map_location="cpu", weights_only=False)
    assert not all(torch.equal(b["state_dict"][k], c["state_dict"][k]) for k in b["state_dict"])
