"""The SLURM profile with config/paper.yaml: what sbatch is asked for, per rule (a fake
sbatch on PATH records each call and refuses it, so nothing runs), and dry-run checks."""

from __future__ import annotations

import os
import re
import stat

import pytest

from workflow_helpers import copy_workflow, limits_overlay, snakemake

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
    # (index_dataset is a local rule: it runs beside Snakemake, never through sbatch.)
    calls = _submissions(workdir, tmp_path / "roots", ["data/generator/prompts.pt", "data/domains/vehicle/shard_0"],
                         ["encode_prompts", "build_domain"], ["data/index/semantickitti.json"])
    calls.update(_submissions(
        workdir, tmp_path / "later",
        ["data/generator/cdts/model.pt", "data/samples/Vehicle/shard_0",
         "data/eval_samples/baseline-Vehicle/ddpm_256/Vehicle/shard_0"],
        ["train_generator", "sample_domain", "sample_eval"],
        ["data/domains/index.json", "data/generator/prompts.pt", "data/generator/full/model.pt",
         "data/generator_single/Vehicle/model.pt"],
    ))
    assert set(calls) == {"encode_prompts", "build_domain", "train_generator", "sample_domain", "sample_eval"}
    for rule in ("encode_prompts", "train_generator", "sample_domain", "sample_eval"):
        assert " -p gpu " in calls[rule] and "--gpus=1" in calls[rule], calls[rule]
    assert " -p cpu " in calls["build_domain"] and "--gpus" not in calls["build_domain"]
    assert "-A testacct" in calls["train_generator"]
    # 500k iterations x 0.58 s x 1.5 + 10 min; a 500-scan DDPM-256 shard: 500 x 3.52 s x 1.5 + 10 min.
    assert " -t 7260 " in calls["train_generator"] and "--cpus-per-task=5" in calls["train_generator"]
    assert " -t 54 " in calls["sample_domain"] and " -t 54 " in calls["sample_eval"]


def _dry_run_resources(workdir, *args):
    out = snakemake(workdir, "--dry-run", *SLURM, "--default-resources", "slurm_account=testacct", *args)
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
    # paper.yaml: text, evaluation and extractor training on cuda ask for a GPU.
    assert {"encode_prompts", "generator_evidence", "generation_quality", "train_generator", "sample_eval",
            "train_supervised", "train_labeler", "train_extractor"} <= gpu
    assert not gpu & {"build_domain", "index_dataset", "domains_index", "gda_curve"}
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


def test_cpu_only_cluster_asks_no_gpu_anywhere(workdir, tmp_path):
    cpu_only = tmp_path / "cpu_only.yaml"
    cpu_only.write_text("resources: {gpus: false}\n")
    res = _dry_run_resources(workdir, *PAPER, str(cpu_only), "--", "results/semkitti_1pct.json",
                             "results/generation_quality.json")
    assert {"train_generator", "train_labeler", "train_supervised", "sample_domain"} <= set(res)
    assert all("gpu" not in r and r["slurm_partition"] == "cpu" for r in res.values()), res


def test_auto_asks_gpus_only_where_the_partition_file_has_them(workdir, tmp_path):
    parts = tmp_path / "parts.yaml"
    parts.write_text("partitions:\n  gpu: {max_gpu: 0}\n  cpu: {max_gpu: 0}\n")
    cfg = tmp_path / "no_gpus.yaml"
    cfg.write_text(f"resources: {{partition_config: {parts}}}\n")
    res = _dry_run_resources(workdir, *PAPER, str(cfg), "--", "data/generator/full/model.pt")
    assert "gpu" not in res["train_generator"] and res["train_generator"]["slurm_partition"] == "cpu"
    # The generator's own device setting: cpu asks no GPU even where the cluster has them.
    cfg.write_text("generator: {training: {device: cpu}}\n")
    res = _dry_run_resources(workdir, *PAPER, str(cfg), "--", "data/generator/full/model.pt")
    assert "gpu" not in res["train_generator"]


def test_memory_follows_the_work_and_a_job_over_its_partition_limit_is_refused(workdir, tmp_path):
    target = ("--", "data/generator/full/model.pt")
    cpu = tmp_path / "cpu.yaml"  # on the CPU the activations count too
    cpu.write_text("resources: {gpus: false}\n")
    small = _dry_run_resources(workdir, "--configfile", "config/test.yaml", str(cpu), *target)["train_generator"]
    bigger = tmp_path / "bigger.yaml"
    bigger.write_text("generator: {training: {batch_size: 64, crop_width: null}, model: {base_channels: 64}}\n")
    big = _dry_run_resources(workdir, "--configfile", "config/test.yaml", str(cpu), str(bigger), *target)["train_generator"]
    assert int(big["mem_mb"]) > int(small["mem_mb"]) + 1000, (small, big)
    # The paper generator trains on a GPU: its host memory is interpreter, data and workers only.
    paper = _dry_run_resources(workdir, *PAPER, *target)["train_generator"]
    assert int(paper["mem_mb"]) < 16000

    parts = tmp_path / "parts.yaml"
    parts.write_text("partitions:\n  gpu: {max_gpu: 1, max_mem_mb: 1000}\n  cpu: {max_mem_mb: 1000}\n")
    limits = tmp_path / "limits.yaml"
    limits.write_text(f"resources: {{partition_config: {parts}}}\n")
    out = snakemake(workdir, "--dry-run", *SLURM, "--default-resources", "slurm_account=testacct",
                    "--configfile", "config/test.yaml", str(limits), *target, check=False)
    text = out.stdout + out.stderr
    assert out.returncode != 0
    assert re.search(r"PartitionLimitExceeded: Rule \w+ asks \d+ MB of memory \(mem_mb\) but partition \w+ allows 1000", text)
    assert not (workdir / "data" / "generator" / "full" / "model.pt").exists()


def test_placeholder_account_stops_a_dry_run_with_one_line(workdir, tmp_path):
    env = {"PATH": f"{tmp_path}:{os.environ['PATH']}"}
    (tmp_path / "scontrol").write_text("#!/bin/sh\necho 'AccountingStorageType   = accounting_storage/slurmdbd'\n")
    (tmp_path / "scontrol").chmod(stat.S_IRWXU)
    old = os.environ.copy()
    os.environ.update(env)
    os.environ.pop("SBATCH_ACCOUNT", None)
    try:
        out = snakemake(workdir, "--dry-run", *SLURM, *PAPER, "--", "results/semkitti_1pct.json", check=False)
        assert out.returncode != 0
        lines = [line for line in (out.stdout + out.stderr).splitlines() if "CHANGE_ME" in line]
        assert len(lines) == 1 and "SBATCH_ACCOUNT" in lines[0] and "workflow/profiles/slurm/config.yaml" in lines[0]
        os.environ["SBATCH_ACCOUNT"] = "myproject"
        res = _dry_run_resources(workdir, *PAPER, "--", "results/semkitti_1pct.json")
        assert res["train_supervised"]["slurm_account"] == "myproject"
        # A cluster without accounting takes any account: the placeholder passes.
        os.environ.pop("SBATCH_ACCOUNT")
        (tmp_path / "scontrol").write_text("#!/bin/sh\necho 'AccountingStorageType   = accounting_storage/none'\n")
        assert snakemake(workdir, "--dry-run", *SLURM, *PAPER, "--", "results/semkitti_1pct.json").returncode == 0
    finally:
        os.environ.clear()
        os.environ.update(old)


def test_paper_dry_run_fits_the_shipped_partition_limits(workdir):
    import yaml

    limits = yaml.safe_load((workdir / "workflow" / "profiles" / "slurm" / "partitions.yaml").read_text())["partitions"]
    res = _dry_run_resources(workdir, *PAPER, "--", "all")
    assert len(res) > 15 and "train_generator" in res
    for rule, r in res.items():
        if "slurm_partition" not in r:  # a local rule (an aggregate of results) runs beside Snakemake
            continue
        part = limits[r["slurm_partition"]]
        assert int(r["runtime"]) <= 7 * 24 * 60, rule  # max_runtime 7-00:00:00
        assert int(r["mem_mb"]) <= part["max_mem_mb"] and int(r["cpus_per_task"]) <= part["max_cpus_per_task"], rule
        assert int(r.get("gpu", 0)) <= part["max_gpu"], rule


def test_paper_generator_training_longer_than_its_partition_runs_as_a_chain_of_segment_jobs(workdir, tmp_path):
    """With a two-day limit on the GPU partition, the paper's ~5-day generator training is cut into
    segment jobs that each fit; the last job writes the weights (a real chain: test_generator_segments)."""
    overlay = limits_overlay(tmp_path, "2-00:00:00", "7-00:00:00")
    target = ("--", "data/generator/full/model.pt")
    out = snakemake(workdir, "--dry-run", *SLURM, "--default-resources", "slurm_account=testacct", *PAPER,
                    str(overlay), *target)
    jobs = re.findall(r"rule (train_generator\w*):.*?output: (\S+).*?runtime=(\d+)", out.stdout, re.S)
    segments = [(out_, int(minutes)) for rule, out_, minutes in jobs if rule == "train_generator_segment"]
    final = [int(minutes) for rule, _, minutes in jobs if rule == "train_generator"]
    assert len(segments) == 2 and len(final) == 1, jobs  # 7,260 minutes in jobs of at most 2,880
    assert all(m <= 2 * 24 * 60 for _, m in segments) and final[0] <= 2 * 24 * 60
    ends = sorted(int(re.search(r"until_(\d+)\.json", o).group(1)) for o, _ in segments)
    assert 0 < ends[0] < ends[1] < 500_000
    # Without the tighter limit (the shipped 7 days) the training is one job.
    plain = snakemake(workdir, "--dry-run", *SLURM, "--default-resources", "slurm_account=testacct", *PAPER, *target)
    assert "train_generator_segment" not in plain.stdout and "rule train_generator:" in plain.stdout


def test_downstream_training_runtimes_follow_their_schedules(tmp_path):
    """Epoch-based trainings ask for epochs x steps per epoch x batch x seconds per scan-step
    (+ margin and set-up), counting the scans in the index of the configured root once it exists
    (a subset: one out of every 100/percent of them)."""
    import json
    import math

    (tmp_path / "wf").mkdir()
    workdir = copy_workflow(tmp_path / "wf")
    target = ("--", "results/semkitti_1pct.json")
    before = _dry_run_resources(workdir, *PAPER, *target)
    assert int(before["train_labeler"]["runtime"]) == 600  # nothing indexed yet: rates.downstream_hours

    index, subset = workdir / "data/index/semantickitti.json", workdir / "data/subsets/semantickitti_1pct.json"
    index.parent.mkdir(parents=True)
    subset.parent.mkdir(parents=True)
    index.write_text(json.dumps({"root": "/datasets/SemanticKITTI/dataset",
                                 "splits": {"train": [{}] * 19130, "val": [{}] * 4071}}))
    subset.write_text(json.dumps({"entries": [{}] * 192}))
    after = _dry_run_resources(workdir, *PAPER, *target)

    def minutes(scans, epochs=15, batch=16, rate=0.09):  # paper.yaml's schedule, rates' defaults
        return math.ceil(10 + 1.5 * epochs * math.ceil(scans / batch) * batch * rate / 60)

    assert int(after["train_labeler"]["runtime"]) == minutes(19130)  # ~11 h: 100 % of the train split
    assert int(after["train_supervised"]["runtime"]) == minutes(192)  # 1 %: minutes, not a flat 10 h
    # An index of another root (the synthetic world's, about to be remade) does not count.
    index.write_text(json.dumps({"root": "data/synthetic/semantickitti", "splits": {"train": [{}] * 20}}))
    assert int(_dry_run_resources(workdir, *PAPER, *target)["train_labeler"]["runtime"]) == 600


def test_an_epoch_schedule_on_a_synthetic_world_not_made_yet_is_planned_from_its_settings(tmp_path):
    """Before the synthetic world exists, an epoch-based labeler asks what its schedule needs over the
    scans the world's settings will write (not rates.downstream_hours), the same as once it is indexed."""
    import json

    (tmp_path / "wf").mkdir()
    workdir = copy_workflow(tmp_path / "wf")
    overlay = tmp_path / "epochs.yaml"
    overlay.write_text("downstream:\n  labeler:\n    schedule: {iterations: null, epochs: 40}\n")
    args = ("--configfile", "config/config.yaml", str(overlay), "--", "data/labeler/semantickitti.pt")
    before = int(_dry_run_resources(workdir, *args)["train_labeler"]["runtime"])
    assert not (workdir / "data/synthetic").exists()
    assert before != 10 * 60  # not the flat rates.downstream_hours

    from omnilidar.config import load_config
    from omnilidar.data.synthetic.shards import planned_split_counts

    cfg = load_config(workdir / "config/config.yaml")
    planned = planned_split_counts("semantickitti", cfg["synthetic"])
    (workdir / "data/index").mkdir(parents=True)
    index = {"root": "data/synthetic/semantickitti", "splits": {k: [{}] * n for k, n in planned.items()}}
    (workdir / "data/index/semantickitti.json").write_text(json.dumps(index))
    assert int(_dry_run_resources(workdir, *args)["train_labeler"]["runtime"]) == before
    index["splits"]["train"] *= 4  # a world four times larger asks more
    (workdir / "data/index/semantickitti.json").write_text(json.dumps(index))
    assert int(_dry_run_resources(workdir, *args)["train_labeler"]["runtime"]) > before


def test_downstream_trainings_longer_than_their_partition_run_as_chains_of_segment_jobs(tmp_path):
    """With a six-hour GPU partition the paper's labeler (~11 h on 19,130 scans) runs as two jobs and
    a Pi3DET detector (80 epochs over 4,000 frames, ~127 h) as 22: each asks its share, within the
    limit; segment k resumes segment k-1 and the training's own job resumes the last one."""
    import json

    (tmp_path / "wf").mkdir()
    workdir = copy_workflow(tmp_path / "wf")
    (workdir / "data/index").mkdir(parents=True)
    (workdir / "data/index/semantickitti.json").write_text(json.dumps(
        {"root": "/datasets/SemanticKITTI/dataset", "splits": {"train": [{}] * 19130, "val": [{}] * 4071}}))
    (workdir / "data/index/pi3det.json").write_text(json.dumps(
        {"root": "/datasets/Pi3DET", "splits": {"drone_train": [{}] * 4000, "drone_val": [{}] * 1000}}))
    overlay = limits_overlay(tmp_path, "06:00:00", "7-00:00:00")
    out = snakemake(workdir, "--dry-run", *SLURM, *PAPER, str(overlay), "--default-resources", "slurm_account=testacct",
                    "--", "data/labeler/semantickitti.pt", "data/detection/drone/pv_rcnn_1pct_real.pt",
                    "data/detection/drone/pv_rcnn_100pct_real.pt").stdout
    jobs = re.findall(r"rule (train_\w+):\n    input: ([^\n]*)\n    output: (\S+).*?runtime=(\d+).*?Shell command: ([^\n]*)",
                      out, re.S)
    by_rule = {}
    for rule, inputs, output, minutes, shell in jobs:
        by_rule.setdefault(rule, []).append((inputs, output, int(minutes), shell))
    assert {k: len(v) for k, v in by_rule.items()} == {
        "train_labeler_segment": 1, "train_labeler": 1, "train_detector_real_segment": 21, "train_detector_real": 2}
    assert all(m <= 360 for runs in by_rule.values() for _, _, m, _ in runs)
    (seg_in, seg_out, _, seg_shell), = by_rule["train_labeler_segment"]
    (final_in, _, _, final_shell), = by_rule["train_labeler"]
    assert seg_out == "data/labeler/segments/semantickitti.1of2.json" and seg_out in final_in
    assert "--segment 1/2" in seg_shell and "--segment" not in final_shell
    assert "--work-dir work/labeler " in seg_shell and "--work-dir work/labeler " in final_shell
    last = [r for r in by_rule["train_detector_real_segment"] if r[1].endswith(".21of22.json")][0]
    assert "data/detection/drone/segments/pv_rcnn_100pct_real.20of22.json" in last[0]
    assert "--work-dir work/data/detection/drone/pv_rcnn_100pct_real " in last[3]
    one_pct = [r for r in by_rule["train_detector_real"] if "1pct" in r[1]][0]
    assert "segments" not in one_pct[0]  # 40 frames: one job


def test_sampling_from_the_student_asks_for_its_steps_and_its_distillation_fits(workdir, tmp_path):
    (tmp_path / "student.yaml").write_text("generator: {sampling: {student: true}}\n")
    target = ("--", "data/samples/Vehicle/shard_0")
    teacher = _dry_run_resources(workdir, *PAPER, *target)
    student = _dry_run_resources(workdir, *PAPER, str(tmp_path / "student.yaml"), *target)
    assert "distill_generator" not in teacher
    distill = student["distill_generator"]
    assert distill["slurm_partition"] == "gpu" and distill["gpu"] == "1"
    # 60k distillation steps of ~5/3 a training step against the generator's 500k: about a fifth.
    assert 0.15 < int(distill["runtime"]) / int(student["train_generator"]["runtime"]) < 0.25
    # A 500-scan shard in the student's 4 DDIM steps instead of DDPM x 256.
    assert int(student["sample_domain"]["runtime"]) < int(teacher["sample_domain"]["runtime"]) / 4


def test_a_distillation_that_calibrates_its_student_asks_for_the_calibration_s_sampling(workdir, tmp_path):
    target = ("--", "data/samples/Vehicle/shard_0")
    runtimes = {}
    for scans in (0, 64, 128):
        overlay = tmp_path / f"calibrated{scans}.yaml"
        overlay.write_text("generator: {sampling: {student: true}, distillation: {return_calibration: %d}}\n" % scans)
        runtimes[scans] = int(_dry_run_resources(workdir, *PAPER, str(overlay), *target)["distill_generator"]["runtime"])
    # Every domain's scans, sampled with the teacher's 256 steps and the student's 4: linear in the scans.
    assert runtimes[0] < runtimes[64] < runtimes[128]
    assert abs((runtimes[128] - runtimes[0]) - 2 * (runtimes[64] - runtimes[0])) <= 2


@pytest.mark.parametrize("term, most", [("adversarial_weight", 4 / 3), ("distribution_matching_weight", 2)])
def test_a_distillation_with_a_last_round_term_asks_for_its_extra_steps(workdir, tmp_path, term, most):
    target = ("--", "data/samples/Vehicle/shard_0")
    runtimes = {}
    for weight in (0, 0.5):
        overlay = tmp_path / f"{term}{weight}.yaml"
        overlay.write_text("generator: {sampling: {student: true}, distillation: {%s: %s}}\n" % (term, weight))
        runtimes[weight] = int(_dry_run_resources(workdir, *PAPER, str(overlay), *target)["distill_generator"]["runtime"])
    # The last of the rounds trains a second network too (a critic at 1.35 of a step, a fake score
    # at 2.3): more, but less than its last round's share of the whole could add.
    assert runtimes[0] < runtimes[0.5] < runtimes[0] * most


def test_a_distillation_whose_teacher_takes_substeps_asks_for_its_first_round_s_passes(workdir, tmp_path):
    target = ("--", "data/samples/Vehicle/shard_0")
    runtimes = {}
    for substeps in (1, 4):
        overlay = tmp_path / f"substeps{substeps}.yaml"
        overlay.write_text("generator: {sampling: {student: true}, distillation: {teacher_substeps: %d}}\n" % substeps)
        runtimes[substeps] = int(_dry_run_resources(workdir, *PAPER, str(overlay), *target)["distill_generator"]["runtime"])
    # The paper's first round of six (10k steps each) runs 2 x 3 more teacher passes a step, each
    # about a quarter of a step (TEACHER_PASS_COST): about a quarter more.
    assert runtimes[4] / runtimes[1] == pytest.approx(1 + 10_000 * 2 * 3 * 0.26 / 60_000, abs=0.01)
