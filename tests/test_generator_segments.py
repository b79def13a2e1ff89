"""A generator training cut into segment jobs (a partition's time limit) ends with the weights of
one uninterrupted run, bit for bit on CPU; a segment resumes its predecessor's state."""

from __future__ import annotations

import shutil

import pytest
import torch

from workflow_helpers import copy_workflow, planned_jobs, snakemake

pytestmark = pytest.mark.slow

MODEL = "data/generator/full/model.pt"
# Five iterations; one costs 12 estimated minutes against a 30-minute partition (no set-up time, no
# margin), so the chain is: iterations 0-2, 2-4, then the final job 4-5.
RUN = "generator: {training: {iterations: 5, checkpoint_interval: 2}}\n"
CHAIN = ("resources: {{gpus: false, setup_min: 0, margin: 1, rates: {{train_step_s: 184320}},\n"
         "            runtime: {{build_domain: 30}}, partition_config: {parts}}}\n")
PARTS = ("partitions:\n"
         "  gpu: {max_runtime: '00:30:00', max_mem_mb: 64000, max_cpus_per_task: 16, max_gpu: 1}\n"
         "  cpu: {max_runtime: '00:30:00', max_mem_mb: 64000, max_cpus_per_task: 16, max_gpu: 0}\n")


def test_segment_chain_equals_an_uninterrupted_generator_training(tmp_path):
    (tmp_path / "parts.yaml").write_text(PARTS)
    (tmp_path / "run.yaml").write_text(RUN)
    (tmp_path / "chain.yaml").write_text(CHAIN.format(parts=tmp_path / "parts.yaml"))
    run = ("--configfile", "config/test.yaml", str(tmp_path / "run.yaml"))
    chain = (*run, str(tmp_path / "chain.yaml"))

    (tmp_path / "whole").mkdir()
    whole = copy_workflow(tmp_path / "whole")
    snakemake(whole, *run, "--", MODEL)
    # The same inputs, generator cut into a chain by the tighter partition.
    shutil.copytree(whole, tmp_path / "chained", symlinks=True)
    chained = tmp_path / "chained"
    shutil.rmtree(chained / "data" / "generator")
    shutil.rmtree(chained / "work" / "generator")
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
