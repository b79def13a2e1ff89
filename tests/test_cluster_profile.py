"""The SLURM profile with config/paper.yaml: what sbatch is asked for, per rule (a fake
sbatch on PATH records each call and refuses it, so nothing runs), and dry-run checks."""

from __future__ import annotations

import os
import re
import stat

import pytest

from workflow_helpers import copy_workflow, snakemake

PAPER = ("--configfile", "config/paper.yaml")
SLURM = ("--workflow-profile", "workflow/profiles/slurm")


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return copy_workflow(tmp_path_factory.mktemp("cluster"))


def _fake_slurm(bin_dir):
    bin_dir.mkdir()
    tools = {
        "sbatch": '#!/bin/sh\necho "$*" >> "$SBATCH_CAPTURE"\necho "fake sbatch: not submitting" >&2\nexit 1\n',
        "sacctmgr": "#!/bin/sh\necho testacct\n",
        "sacct": "#!/bin/sh\nexit 0\n",
        "squeue": "#!/bin/sh\nexit 0\n",
    }
    for name, text in tools.items():
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(stat.S_IRWXU)


def _submissions(workdir, tmp_path, targets, allowed, inputs):
    """{rule: sbatch arguments} of the jobs a SLURM run submits for ``targets``."""
    for path in inputs:
        (workdir / path).parent.mkdir(parents=True, exist_ok=True)
        (workdir / path).touch()
    tmp_path.mkdir()
    _fake_slurm(tmp_path / "bin")
    capture = tmp_path / "sbatch.txt"
    env = {"PATH": f"{tmp_path / 'bin'}:{os.environ['PATH']}", "SBATCH_CAPTURE": str(capture)}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        snakemake(workdir, *SLURM, *PAPER, "--keep-going", "--retries", "0", "--default-resources",
                  "slurm_account=testacct", "--slurm-init-seconds-before-status-checks", "1",
                  "--allowed-rules", *allowed, "--", *targets, check=False)
    finally:
        for k, v in old.items():
            os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
    calls = {}
    for line in capture.read_text().splitlines():
        rule = re.search(r"--comment rule_(\w+?)(_wildcards|\s)", line).group(1)
        calls[rule] = line.split("--wrap", 1)[0]
    return calls


def test_sbatch_places_each_rule_on_its_partition_with_derived_requests(tmp_path):
    (tmp_path / "wf").mkdir()
    workdir = copy_workflow(tmp_path / "wf")  # its own copy: it puts input files in place
    # First jobs of the DAG (nothing built yet), then jobs whose inputs are put in place.
    calls = _submissions(workdir, tmp_path / "roots", ["data/generator/prompts.pt", "data/index/semantickitti.json"],
                         ["encode_prompts", "index_dataset"], [])
    calls.update(_submissions(
        workdir, tmp_path / "later",
        ["data/generator/cdts/model.pt", "data/samples/Vehicle/shard_0",
         "data/eval_samples/baseline-Vehicle/ddpm_256/Vehicle/shard_0"],
        ["train_generator", "sample_domain", "sample_eval"],
        ["data/domains/index.json", "data/generator/prompts.pt", "data/generator/full/model.pt",
         "data/generator_single/Vehicle/model.pt"],
    ))
    assert set(calls) == {"encode_prompts", "index_dataset", "train_generator", "sample_domain", "sample_eval"}
    for rule in ("encode_prompts", "train_generator", "sample_domain", "sample_eval"):
        assert " -p gpu " in calls[rule] and "--gpus=1" in calls[rule], calls[rule]
    assert " -p cpu " in calls["index_dataset"] and "--gpus" not in calls["index_dataset"]
    assert "-A testacct" in calls["train_generator"]
    # 500k iterations x 0.58 s x 1.5 + 10 min; a 500-scan DDPM-256 shard: 500 x 3.52 s x 1.5 + 10 min.
    assert " -t 7260 " in calls["train_generator"] and "--cpus-per-task=5" in calls["train_generator"]
    assert " -t 54 " in calls["sample_domain"] and " -t 54 " in calls["sample_eval"]


def _dry_run_resources(workdir, *args):
    out = snakemake(workdir, "--dry-run", *SLURM, *args)
    res = {}
    for block in re.split(r"\n(?=\[.*\]\n\s*(?:local)?rule )", out.stdout + out.stderr):
        rule, line = re.search(r"rule (\w+):", block), re.search(r"resources: (.*)", block)
        if rule and line:
            res.setdefault(rule.group(1), dict(kv.split("=", 1) for kv in line.group(1).split(", ") if "=" in kv))
    return res


def test_paper_dry_run_every_job_on_the_right_partition(workdir):
    res = _dry_run_resources(workdir, *PAPER, "--", "results/generation_quality.json", "results/ablation.json",
                             "results/kitti360_generation.json", "results/generator_evidence.json",
                             "results/semkitti_1pct.json")
    for rule, r in res.items():
        assert r["slurm_partition"] == ("gpu" if "gpu" in r else "cpu"), (rule, r)
    gpu = {rule for rule, r in res.items() if "gpu" in r}
    # paper.yaml: text.device cuda and evaluation.device cuda ask for a GPU; extractors train on the CPU.
    assert {"encode_prompts", "generator_evidence", "generation_quality", "train_generator", "sample_eval",
            "train_supervised", "train_labeler"} <= gpu
    assert not gpu & {"build_domain", "index_dataset", "train_extractor", "domains_index", "gda_curve"}
    # Workers + 1 (downstream.schedule.num_workers is 8 in paper.yaml).
    assert res["train_supervised"]["cpus_per_task"] == "9"
    # Tables only score; sampling 2 x 10k scans x 8 domains (~156 h at 3.52 s per scan) is in
    # one-hour shard jobs of 500 scans.
    assert int(res["generation_quality"]["runtime"]) < 156 * 60 / 4
    assert int(res["sample_eval"]["runtime"]) <= 60 and int(res["sample_domain"]["runtime"]) <= 60


def test_cpu_text_device_asks_no_gpu_and_multi_gpu_generator_uses_torchrun(workdir, tmp_path):
    extra = tmp_path / "four_gpus.yaml"
    extra.write_text("generator: {text: {device: cpu}}\nresources: {generator_gpus: 4}\n")
    res = _dry_run_resources(workdir, *PAPER, str(extra), "--", "data/generator/full/model.pt")
    assert "gpu" not in res["encode_prompts"] and res["encode_prompts"]["slurm_partition"] == "cpu"
    assert res["train_generator"]["gpu"] == "4" and res["train_generator"]["cpus_per_task"] == "20"
    out = snakemake(workdir, "--dry-run", "-p", *PAPER, str(extra), "--", "data/generator/full/model.pt")
    assert "torchrun --standalone --nproc_per_node 4 $(which omnilidar) train-generator" in out.stdout
