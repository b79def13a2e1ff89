"""The Snakemake workflow: lint, DAG shape, profiles, real runs and reruns."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
import yaml

from omnilidar.config import load_config
from workflow_helpers import ROOT, copy_workflow, embedded_default, planned_jobs, rerun_reasons, snakemake, synthesized_shards

TINY = "config/test.yaml"
DATASETS = ("semantickitti", "kitti360", "pi3det", "nuscenes")


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return copy_workflow(tmp_path_factory.mktemp("wf"))


def _shard_counts(config: dict) -> dict[str, int]:
    """Synthesize jobs per dataset: one per sequence, platform or split."""
    synth = config["synthetic"]["datasets"]
    return {
        "semantickitti": len(synth["semantickitti"]["sequences"]),
        "kitti360": len(synth["kitti360"]["sequences"]),
        "pi3det": len(synth["pi3det"]["platforms"]),
        "nuscenes": len(synth["nuscenes"]["splits"]),
    }


def test_lint_is_clean(workdir):
    out = snakemake(workdir, "--lint", check=False)
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.mark.parametrize("configfile", ["config/config.yaml", TINY])
def test_data_summary_dag_has_one_job_per_shard(workdir, configfile):
    config = load_config(workdir / configfile)
    jobs = planned_jobs(workdir, "results/data_summary.json", "--configfile", configfile)
    shards = _shard_counts(config)
    assert jobs == {"synthesize": sum(shards.values()), "index_dataset": 4, "data_summary": 1}
    assert synthesized_shards(workdir, "results/data_summary.json", "--configfile", configfile) == shards
    # Sharded, not one job per scan: the embedded default stays a small DAG.
    assert sum(jobs.values()) < 60


def test_embedded_default_job_counts_are_pinned(workdir):
    assert synthesized_shards(workdir, "results/data_summary.json")["semantickitti"] == 13  # 00-12: train, val 08, two test
    assert planned_jobs(workdir, "results/data_summary.json")["index_dataset"] == 4


def test_real_roots_are_indexed_not_generated(workdir, tmp_path):
    cfg = tmp_path / "real.yaml"
    cfg.write_text(yaml.safe_dump({"datasets": {d: {"root": str(tmp_path / d)} for d in DATASETS}}))
    jobs = planned_jobs(workdir, "results/data_summary.json", "--configfile", str(cfg))
    assert jobs == {"index_dataset": 4, "data_summary": 1}


def test_unknown_config_key_fails_before_any_job(workdir, tmp_path):
    cfg = tmp_path / "typo.yaml"
    cfg.write_text("synthetic_typo: 1\n")
    out = snakemake(workdir, "--dry-run", "results/data_summary.json", "--configfile", str(cfg), check=False)
    assert out.returncode != 0
    assert "synthetic_typo" in out.stdout + out.stderr


def test_slurm_profile_asks_gpus_for_gpu_rules_only(workdir):
    out = snakemake(workdir, "--dry-run", "samples", "--workflow-profile", "workflow/profiles/slurm",
                    "--default-resources", "slurm_account=testacct")
    text = out.stdout + out.stderr
    jobs = re.split(r"\n(?=\[.*\]\n\s*rule |rule )", text)
    resources = {}
    for block in jobs:
        rule = re.search(r"rule (\w+):", block)
        res = re.search(r"resources: (.*)", block)
        if rule and res:
            resources.setdefault(rule.group(1), res.group(1))
    assert "gpu=1" in resources["train_generator"] and "gpu=1" in resources["sample_domain"]
    assert "gpu" not in resources["synthesize"] and "gpu" not in resources["build_domain"]
    assert "slurm_account=" in resources["train_generator"]


def test_paper_config_plans_paper_scale_shards(workdir):
    config = load_config(workdir / "config" / "paper.yaml")
    jobs = planned_jobs(workdir, "results/semkitti_1pct.json", "--configfile", "config/paper.yaml")
    sampling = config["generator"]["sampling"]
    assert sampling["scans_per_domain"] == 10000 and config["generator"]["training"]["iterations"] == 500000
    assert jobs["sample_domain"] == sampling["scans_per_domain"] // sampling["scans_per_shard"]  # Vehicle only
    assert "synthesize" not in jobs and jobs["index_dataset"] >= 1  # real roots are indexed


def test_generator_jobs_run_torch_on_the_threads_snakemake_gives_them(workdir):
    """Training, distilling and sampling the generator get `--threads {threads}` like every downstream
    job: with torch's default (every core) beside another job they stalled at OpenMP barriers
    (benchmarks/bench_sampling_threads.py)."""
    out = snakemake(workdir, "--dry-run", "--printshellcmds", "results/tradeoff.json", "results/semkitti_1pct.json",
                    "--configfile", TINY, "config/student.yaml").stdout
    commands = [line for line in out.splitlines()
                if re.search(r"omnilidar (sample|train-generator|distill-generator) ", line)]
    kinds = {re.search(r"omnilidar (\S+) ", line)[1] for line in commands}
    assert kinds == {"sample", "train-generator", "distill-generator"}, kinds
    assert all(" --threads 1 " in line for line in commands)


def test_generator_dag_shards_sampling(workdir):
    config = load_config(workdir / "config" / "config.yaml")
    jobs = planned_jobs(workdir, "samples")
    sampling = config["generator"]["sampling"]
    shards = -(-sampling["scans_per_domain"] // sampling["scans_per_shard"])
    assert jobs["train_generator"] == 1 and jobs["encode_prompts"] == 1
    assert jobs["sample_domain"] == 8 * shards
    assert jobs["build_domain"] == sum(config["domains"][d]["num_shards"] for d in config["domains"]
                                       if "num_shards" in config["domains"][d])


def _edit_config(wd, change):
    cfg = yaml.safe_load((wd / TINY).read_text())
    change(cfg)
    (wd / TINY).write_text(yaml.safe_dump(cfg))


@pytest.mark.slow
def test_tiny_workflow_runs_and_reruns_only_what_changed(tmp_path):
    """One real run of data, domains, generator and sampling on the tiny config,
    then dry runs after each kind of change (settings, code, comments)."""
    wd = copy_workflow(tmp_path)
    original = (wd / TINY).read_text()
    target = ("results/data_summary.json", "samples", "--configfile", TINY)
    snakemake(wd, *target)

    summary = yaml.safe_load((wd / "results" / "data_summary.json").read_text())
    assert summary["experiment"] == "data_summary"
    assert summary["data_source"]["semantickitti"]["kind"] == "synthetic"
    assert summary["data_source"]["semantickitti"]["root"].endswith("synthetic/semantickitti")
    # Points per scan against real KITTI: test_synthetic_world (it needs the real samples).
    assert (wd / "results" / "figures" / "data_summary.png").stat().st_size > 1000
    assert len(list((wd / "data" / "samples" / "Drone" / "shard_0" / "velodyne").glob("*.bin"))) == 2
    assert planned_jobs(wd, *target) == {}, "a finished workflow plans nothing"

    # A comment and a docstring in the synthetic world's and the generator's code: nothing reruns.
    for f in (wd / "omnilidar" / "data" / "synthetic" / "raycast.py", wd / "omnilidar" / "generator" / "unet.py"):
        text = f.read_text()
        assert text.startswith('"""')
        f.write_text(text.replace('"""', '"""Edited docstring. ', 1).replace("\n\n", "\n\n# an edited comment\n", 1))
    assert planned_jobs(wd, *target) == {}

    # Sampling settings: resample only, never retrain.
    _edit_config(wd, lambda c: c["generator"]["sampling"].update(steps=3))
    jobs = planned_jobs(wd, *target)
    assert set(jobs) == {"sample_domain", "samples"}, jobs
    assert jobs["sample_domain"] == 8
    assert re.search(r"reason: .*[Pp]arams", rerun_reasons(wd, *target))
    (wd / TINY).write_text(original)
    assert planned_jobs(wd, *target) == {}

    # Generator architecture: retrain and resample, but neither prompts nor domains.
    _edit_config(wd, lambda c: c["generator"]["model"].update(base_channels=16))
    assert planned_jobs(wd, *target) == {"train_generator": 1, "sample_domain": 8, "samples": 1}
    _edit_config(wd, lambda c: c["generator"]["model"].update(base_channels=8))

    # One domain's effect settings: that domain only, then the generator.
    fog = dict(yaml.safe_load((wd / TINY).read_text())["domains"]["fog"])
    _edit_config(wd, lambda c: c["domains"]["fog"].update(effects=[{"name": "fog", "severities": ["heavy"]}]))
    jobs = planned_jobs(wd, *target)
    assert jobs.get("build_domain") == 1 and "synthesize" not in jobs, jobs
    assert jobs["train_generator"] == 1
    _edit_config(wd, lambda c: c["domains"].update(fog=fog))

    # Code of one effect: only the domains using it rebuild.
    fog_py = wd / "omnilidar" / "domains" / "effects" / "fog.py"
    fog_py.write_text(fog_py.read_text() + "\n_EDITED = True\n")
    jobs = planned_jobs(wd, *target)
    assert jobs.get("build_domain") == 1, jobs
    assert "synthesize" not in jobs and "encode_prompts" not in jobs

    # Settings of the summary only: only the summary reruns (plus the fog cascade above).
    _edit_config(wd, lambda c: c["data_summary"].update(max_scans=3))
    assert planned_jobs(wd, "results/data_summary.json", "--configfile", TINY) == {"data_summary": 1}

    # Code of the index stage: index and summary rerun, synthesis does not.
    index_py = wd / "omnilidar" / "data" / "index.py"
    index_py.write_text(index_py.read_text() + "\n_EDITED = True\n")
    jobs = planned_jobs(wd, "results/data_summary.json", "--configfile", TINY)
    assert set(jobs) == {"index_dataset", "data_summary"}, jobs

    # The root seed: every generation job and everything downstream.
    _edit_config(wd, lambda c: c.update(seed=1))
    jobs = planned_jobs(wd, "results/data_summary.json", "--configfile", TINY)
    shards = sum(_shard_counts(load_config(wd / TINY)).values())
    assert jobs == {"synthesize": shards, "index_dataset": 4, "data_summary": 1}


@pytest.mark.slow
def test_one_gpu_profile_plans_full_resolution_and_runs_tiny_on_the_cpu(tmp_path):
    """config/gpu.yaml laid over the default: the generator on whole 64 x 1024 sweeps, a wider labeler
    trained longer, the students' regime unchanged. Laid over the tiny config with tiny sizes, its
    model and schedule settings train and sample for real on the CPU (devices stay `auto`)."""
    wd = copy_workflow(tmp_path)
    args = ("results/semkitti_1pct.json", "results/gda_decomposition.json",
            "--configfile", "config/config.yaml", "config/gpu.yaml")
    out = snakemake(wd, "--dry-run", "--printshellcmds", *args).stdout
    train = next(line for line in out.splitlines() if "omnilidar train-generator" in line)
    assert '"height": 64' in train and '"width": 1024' in train and '"crop_width": null' in train
    assert '"iterations": 2500' in train and '"base_channels": 32' in train
    labeler = next(line for line in out.splitlines() if "omnilidar train-labeler" in line)
    assert '"width": "W32"' in labeler and '"iterations": 1000' in labeler
    students = [line for line in out.splitlines() if "omnilidar train-segmentor" in line]
    default = embedded_default(wd)["downstream"]["schedule"]["iterations"]
    assert students and all(f'"iterations": {default}' in line and '"voxel_size": 0.3' in line for line in students)
    assert all('"device": "auto"' in line for line in students + [labeler])
    assert "omnilidar round-trip-pool vehicle" in out and '"width": 1024' in out.split("round-trip-pool")[1][:600]
    # The same keys, tiny: a real generator training and sampling, and a real labeler, on the CPU.
    (wd / "tiny_gpu.yaml").write_text(yaml.safe_dump({
        "domains": {"range_image": {"height": 32, "width": 256}},
        "generator": {"range_image": {"height": 32, "width": 256}, "model": {"base_channels": 8},
                      "training": {"iterations": 2, "batch_size": 2, "warmup_iters": 1, "checkpoint_interval": 1,
                                   "log_interval": 1, "num_workers": 0},
                      "sampling": {"steps": 2, "batch_size": 2, "scans_per_domain": 2, "scans_per_shard": 2}},
        "downstream": {"labeler": {"schedule": {"iterations": 2, "checkpoint_interval": 1, "log_interval": 1}}},
    }))
    snakemake(wd, "data/samples/Vehicle/shard_0", "data/labeler/semantickitti.val.json",
              "--configfile", TINY, "config/gpu.yaml", "tiny_gpu.yaml")
    assert len(list((wd / "data" / "samples" / "Vehicle" / "shard_0" / "velodyne").glob("*.bin"))) == 2
    scores = yaml.safe_load((wd / "data" / "labeler" / "semantickitti.val.json").read_text())
    assert scores["model"]["width"] == "W32" and 0.0 <= scores["sets"]["val"]["miou"] <= 1.0


def test_every_result_target_plans_from_an_empty_working_directory(tmp_path):
    """The way snakedeploy and the Snakemake catalog run a workflow: --snakefile from elsewhere.
    Shipped files (config, schemas, detector yamls) are found relative to the workflow."""
    rules_text = "".join(p.read_text() for p in sorted((ROOT / "rules").glob("*.smk")))
    targets = sorted({t.replace("{pct}", "1").replace("{platform}", "drone")
                      for t in re.findall(r'^ *json="(results/[^"]*\.json)",$', rules_text, re.M)})
    assert len(targets) > 10
    empty = tmp_path / "elsewhere"
    empty.mkdir()
    out = subprocess.run([sys.executable, "-m", "snakemake", "-n", "-j4", "--snakefile", str(ROOT / "Snakefile"),
                          "--directory", str(empty), "all", *targets, "--quiet", "rules"],
                         cwd=empty, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    assert "train_detector_real" in out.stdout + out.stderr
    assert sorted(p.name for p in empty.iterdir()) == [".snakemake"]


def test_a_dataset_root_that_does_not_exist_is_warned_about_in_a_dry_run(workdir, tmp_path):
    (tmp_path / "kitti").mkdir()
    cfg = tmp_path / "roots.yaml"
    cfg.write_text(yaml.safe_dump({"datasets": {"semantickitti": {"root": str(tmp_path / "kitti")},
                                                "nuscenes": {"root": str(tmp_path / "no_such_dir")}}}))
    out = snakemake(workdir, "--dry-run", "results/data_summary.json", "--configfile", str(cfg))
    lines = [line for line in (out.stdout + out.stderr).splitlines() if "does not exist" in line]
    assert lines == [f"Warning: datasets.nuscenes.root {tmp_path / 'no_such_dir'} does not exist: every target that "
                     "reads nuscenes will fail at its index job (set the root, or null for the synthetic world)"]
