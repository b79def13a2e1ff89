"""The segmentation GDA stage in the workflow: DAG shape of the targets and what
reruns when a downstream or a generator setting changes (dry runs)."""

from __future__ import annotations

import math

import pytest
import yaml

from workflow_helpers import copy_workflow, embedded_default, plan_with_change, planned_jobs, synthesized_shards

# Used only while rules/generator.smk is not in the checkout: the sampling rule's
# contract (rule sample_domain, sample_shards(domain)) with the generator's settings
# as its params, sampling replaced by copying a domain shard's scans.
GENERATOR_STUB = '''
def sample_shards(domain):
    n = -(-config["generator"]["sampling"]["scans_per_domain"] // config["generator"]["sampling"]["scans_per_shard"])
    return [f"{DATA}/samples/{domain}/shard_{k}" for k in range(n)]


rule sample_domain:
    input:
        f"{DATA}/domains/{{domain}}/shard_0",
    output:
        directory(f"{DATA}/samples/{{domain}}/shard_{{shard}}"),
    params:
        settings=settings("generator"),
    log:
        "logs/samples/{domain}_{shard}.log",
    shell:
        "mkdir -p {output}/velodyne > {log} 2>&1"
'''


def wire_downstream(workdir):
    """Include the domain, generator and downstream rules in a workflow copy
    (and their config sections) when the checkout does not yet."""
    snakefile = workdir / "Snakefile"
    text = snakefile.read_text()
    includes = ["rules/domains.smk"]
    if (workdir / "rules" / "generator.smk").exists():
        includes.append("rules/generator.smk")
    else:
        (workdir / "rules" / "generator_stub.smk").write_text(GENERATOR_STUB)
        includes.append("rules/generator_stub.smk")
    includes.append("rules/downstream.smk")
    for inc in includes:
        if inc not in text:
            text = text.replace("\n\nrule all:", f'\ninclude: "{inc}"\n\n\nrule all:', 1)
    snakefile.write_text(text)
    schema = workdir / "workflow" / "schemas" / "config.schema.yaml"
    doc = yaml.safe_load(schema.read_text())
    for section in ("domains", "generator", "downstream"):
        if section not in doc["properties"]:
            schema.write_text(schema.read_text().rstrip("\n") + f"\n  {section}:\n    $ref: {section}.schema.yaml\n")
    return workdir


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return wire_downstream(copy_workflow(tmp_path_factory.mktemp("wf_downstream")))


def _jobs(workdir, *args):
    return planned_jobs(workdir, *args)


def test_headline_dag(workdir):
    jobs = _jobs(workdir, "results/semkitti_1pct.json")
    assert jobs["train_labeler"] == 1 and jobs["evaluate_labeler"] == 1  # its own val scores join the result
    assert jobs["train_supervised"] == 2 and jobs["train_gda"] == 2  # MinkUNet, SPVCNN
    assert jobs["train_supervised_seed"] == jobs["train_gda_seed"] == 2  # and each with a second seed
    assert jobs["evaluate_segmentor"] == 8
    assert jobs["make_subset"] == 1 and jobs["semkitti_result"] == 1
    assert jobs["pseudo_label"] == jobs["sample_domain"] >= 1
    # Only the Vehicle domain is sampled; nothing of nuScenes or the corrupted sets.
    assert "build_corrupted" not in jobs
    assert "nuscenes" not in synthesized_shards(workdir, "results/semkitti_1pct.json")


def test_extra_seeds_are_their_own_runs(workdir):
    """experiments.semkitti.seeds: 3 trains every run with seeds 0, 1, 2 (files _seed1, _seed2) and
    scores them all in one result."""
    from workflow_helpers import snakemake

    (workdir / "seeds.yaml").write_text("downstream: {experiments: {semkitti: {seeds: 3}}}\n")
    out = snakemake(workdir, "--dry-run", "--printshellcmds", "results/semkitti_1pct.json",
                    "--configfile", "config/config.yaml", "seeds.yaml").stdout
    jobs = _jobs(workdir, "results/semkitti_1pct.json", "--configfile", "config/config.yaml", "seeds.yaml")
    assert jobs["train_supervised"] == jobs["train_gda"] == 2
    assert jobs["train_supervised_seed"] == jobs["train_gda_seed"] == 4 and jobs["evaluate_segmentor"] == 12
    runs = {line.split("--seed ")[1].split()[0] + " " + line.split("--out ")[1].split()[0]
            for line in out.splitlines() if "omnilidar train-segmentor" in line}
    assert "1 data/segmentation/semantickitti/minkunet_1pct_real_seed1.pt" in runs
    assert "2 data/segmentation/semantickitti/spvcnn_1pct_gda-vehicle_seed2.pt" in runs
    assert "0 data/segmentation/semantickitti/minkunet_1pct_real.pt" in runs and len(runs) == 12
    result = next(line for line in out.splitlines() if "omnilidar gda-result" in line)
    assert "minkunet_1pct_gda-vehicle_seed2.val.json" in result and "labeler/semantickitti.val.json" in result
    # The GDA curve: every count (and its 0 point, the supervised-only run) for each seed.
    (workdir / "curve_seeds.yaml").write_text("downstream: {experiments: {gda_curve: {seeds: 2}}}\n")
    jobs = _jobs(workdir, "results/gda_curve.json", "--configfile", "config/config.yaml", "curve_seeds.yaml")
    assert jobs["train_gda_curve"] == jobs["train_gda_curve_seed"] == 3  # 4, 8, 16 generated scans
    assert jobs["train_supervised"] == jobs["train_supervised_seed"] == 1
    # The real series too: first 4, 8, 16 pool scans, true and pseudo-labels, each seed.
    assert jobs["train_curve_pool"] == jobs["train_curve_pool_seed"] == 6
    assert jobs["evaluate_segmentor"] == 2 * (1 + 3 + 6)


def test_every_target_plans(workdir):
    jobs = _jobs(workdir, "segmentation")
    # semkitti 1/10/20: 2 backbones x 2 runs each; semkittic and semanticstf share the
    # 100 % supervised-only MinkUNet; nuScenes 1/10/20/100: 2 x 2 each.
    assert jobs["train_supervised"] == 3 * 2 + 1 + 4 * 2
    assert jobs["train_gda"] == 3 * 2 + 1 + 1 + 4 * 2
    assert jobs["train_labeler"] == 1
    assert jobs["build_corrupted"] == 12
    assert jobs["make_subset"] == 3 + 1 + 4
    assert {"semkitti_result", "semkittic_result", "nusc_beam32_result", "semanticstf_result"} <= set(jobs)


def test_supervised_runs_and_labeler_take_no_generator_input(workdir):
    jobs = _jobs(workdir, "data/segmentation/semantickitti/minkunet_1pct_real.pt", "data/labeler/semantickitti.pt")
    assert "sample_domain" not in jobs and "train_generator" not in jobs and "build_domain" not in jobs
    assert jobs["train_supervised"] == 1 and jobs["train_labeler"] == 1



def test_importing_a_labeler_is_a_small_cpu_job(workdir):
    """Training the labeler asks for the GPU job; importing a checkpoint does not."""
    from workflow_helpers import snakemake

    (workdir / "user_labeler.pt").write_bytes(b"")
    trained = snakemake(workdir, "--dry-run", "data/labeler/semantickitti.pt").stdout
    imported = snakemake(workdir, "--dry-run", "data/labeler/semantickitti.pt",
                         "--config", 'downstream={"labeler": {"checkpoint": "user_labeler.pt"}}').stdout
    # Its schedule (config.yaml's steps x 2 scans x 0.09 s per scan-step on a GPU), x 1.5 + 10 min set-up.
    steps = embedded_default(workdir)["downstream"]["labeler"]["schedule"]["iterations"]
    minutes = math.ceil(steps * 2 * 0.09 * 1.5 / 60 + 10)
    assert f"runtime={minutes}, cpus_per_task=1, slurm_partition=gpu, gpu=1" in trained
    assert "runtime=15, cpus_per_task=1, slurm_partition=cpu, mem_mb=4000" in imported
    assert "gpu=" not in imported.split("rule train_labeler:")[-1] and "input: user_labeler.pt" in imported

def _fake_completed_run(workdir, target, cfg, tmp_path):
    """Run the target's whole DAG with the fake CLI, so the next dry run shows only
    what a config change reruns."""
    from workflow_helpers import run_with_fake_cli

    run_with_fake_cli(workdir, tmp_path / "fakebin", target, "--configfile", str(cfg))
    assert _jobs(workdir, target, "--configfile", str(cfg)) == {}


@pytest.fixture(scope="module")
def completed(tmp_path_factory):
    wd = wire_downstream(copy_workflow(tmp_path_factory.mktemp("wf_rerun")))
    cfg = wd / "rerun.yaml"
    cfg.write_text(yaml.safe_dump({"seed": 0}))
    _fake_completed_run(wd, "results/semkitti_1pct.json", cfg, tmp_path_factory.mktemp("fake"))
    return wd, cfg


def _with_change(wd, cfg, change: dict):
    return plan_with_change(wd, cfg, change, "results/semkitti_1pct.json")


def test_downstream_change_reruns_only_runs_and_evaluation(completed):
    wd, cfg = completed
    jobs = _with_change(wd, cfg, {"downstream.schedule.iterations": 41})
    assert set(jobs) == {"train_supervised", "train_supervised_seed", "train_gda", "train_gda_seed",
                         "evaluate_segmentor", "semkitti_result"}  # two seeds per run


def test_naming_another_held_out_split_rebuilds_nothing_of_the_gda_chain(completed):
    """heldout_split is read only by the held-out sets (the sampler study's real scans): the domain
    builds, the generator and every run stay as they are."""
    wd, cfg = completed
    assert _with_change(wd, cfg, {"domains.fog.heldout_split": "test"}) == {}
    assert "build_domain" in _with_change(wd, cfg, {"domains.fog.split": "val"})  # the check can fail


def test_mixing_change_reruns_only_gda_runs(completed):
    wd, cfg = completed
    jobs = _with_change(wd, cfg, {"downstream.mixing.mode": "ratio"})
    assert set(jobs) == {"train_gda", "train_gda_seed", "evaluate_segmentor", "semkitti_result"}
    assert jobs["evaluate_segmentor"] == 4  # 2 backbones x 2 seeds


def test_labeler_change_reruns_labeler_pseudo_labels_and_gda_not_supervised(completed):
    wd, cfg = completed
    jobs = _with_change(wd, cfg, {"downstream.labeler.schedule.iterations": 81})
    assert {"train_labeler", "evaluate_labeler", "pseudo_label", "train_gda"} <= set(jobs)
    assert "train_supervised" not in jobs and "sample_domain" not in jobs


def test_generator_change_spares_supervised_runs_and_labeler(completed):
    wd, cfg = completed
    jobs = _with_change(wd, cfg, {"generator.sampling.steps": 21})
    assert {"sample_domain", "pseudo_label", "train_gda", "semkitti_result"} <= set(jobs)
    assert "train_supervised" not in jobs and "train_labeler" not in jobs and "evaluate_labeler" not in jobs
    assert jobs["evaluate_segmentor"] == 4  # the GDA runs' evaluations only (2 backbones x 2 seeds)


def test_decomposition_plans_every_row_backbone_and_seed(workdir):
    """results/gda_decomposition.json: 7 rows x 2 backbones x 3 seeds on the study's own regime, the
    pool made once and labelled once, sent once through the generator's range image and back (and
    that labelled once); the generated row takes the first N sampled scans."""
    from workflow_helpers import snakemake

    jobs = _jobs(workdir, "results/gda_decomposition.json")
    assert jobs["train_study"] == 7 * 2 * 3 and jobs["evaluate_segmentor"] == 42
    assert jobs["round_trip_pool"] == jobs["pseudo_label_round_trip"] == 1
    assert jobs["evaluate_labeler"] == jobs["make_pool"] == jobs["pseudo_label_pool"] == jobs["gda_decomposition"] == 1
    assert "train_supervised" not in jobs and "train_gda" not in jobs  # the quick-start runs are not the study's
    assert jobs["make_heldout"] == 1  # whole train sequences outside subset and pool: the regime is checked there
    assert jobs["sample_domain"] == 3  # N = 48 Vehicle scans: three shards of 16, past scans_per_domain
    (workdir / "study.yaml").write_text(
        "downstream: {experiments: {gda_decomposition: {training: {schedule: {iterations: 123}}}}}\n")
    out = snakemake(workdir, "--dry-run", "--printshellcmds", "results/gda_decomposition.json",
                    "--configfile", "config/config.yaml", "study.yaml").stdout
    runs = [line for line in out.splitlines() if "omnilidar train-segmentor" in line]
    assert len(runs) == 42 and all('"iterations": 123' in line for line in runs)
    trips = [line for line in runs if "--pool-source round_trip" in line]
    assert len(trips) == 12
    assert all("--pool data/subsets/round_trip/vehicle_1pct_pool48/pool.json" in line for line in trips)
    assert sum("--pool-labels data/pseudo_labels/pool/round_trip_vehicle_1pct_pool48" in line for line in trips) == 6
    assert "omnilidar round-trip-pool vehicle" in out and '"width": 512' in out
    lasermix = [line for line in runs if "--lasermix" in line]
    assert len(lasermix) == 6 and all("--pool-labels data/pseudo_labels/pool/semantickitti_1pct_pool48" in line
                                      for line in lasermix)
    assert sum("--max-generated 48" in line and "data/samples/Vehicle/shard_2" in line for line in runs) == 6
    assert "spvcnn_1pct_study-truth48_seed2.pt" in out and "minkunet_1pct_study-real48_seed0.pt" in out
    evaluations = [line for line in out.splitlines() if "omnilidar evaluate-segmentor" in line and "study-" in line]
    scored_heldout = [line for line in evaluations
                      if "--split val --subset-set heldout=data/subsets/semantickitti_1pct_heldout20.json" in line]
    assert len(evaluations) == len(scored_heldout) == 42
    assert "--exclude data/subsets/semantickitti_1pct.json --whole-sequences --count 20" in out
    assert ("--exclude data/subsets/semantickitti_1pct.json --heldout data/subsets/semantickitti_1pct_heldout20.json "
            "--count 48" in out)
    # The study's regime leaves the quick-start target's runs alone.
    headline = snakemake(workdir, "--dry-run", "--printshellcmds", "results/semkitti_1pct.json",
                         "--configfile", "config/config.yaml", "study.yaml").stdout
    trains = [line for line in headline.splitlines() if "omnilidar train-segmentor" in line]
    assert len(trains) == 8 and not any('"iterations": 123' in line for line in trains)
    # Each attempt (the shipped remedies file) trains the generated row again, on its own overrides,
    # is scored on val, and joins the result.
    out = snakemake(workdir, "--dry-run", "--printshellcmds", "results/gda_decomposition.json",
                    "--configfile", "config/config.yaml", "config/decomposition_attempts.yaml").stdout
    tried = [line for line in out.splitlines()
             if "omnilidar train-segmentor" in line and "study-gda-vehicle-share25" in line]
    assert len(tried) == 6 and all('"generated_share": 0.25' in line and "--max-generated 48" in line for line in tried)
    assert sum('"min_confidence": 0.6' in line for line in out.splitlines() if "omnilidar train-segmentor" in line) == 6
    result = next(line for line in out.splitlines() if "omnilidar gda-decomposition" in line)
    assert result.count("--attempt share25=") == result.count("--attempt confident=") == 6


def _attempts_overlay(workdir, name, attempts):
    """Snakemake arguments of the decomposition (MinkUNet only) with an overlay holding these
    attempts (flow-style YAML), written to <name>.yaml."""
    (workdir / f"{name}.yaml").write_text(
        f"downstream: {{experiments: {{gda_decomposition: {{backbones: [minkunet], attempts: {{{attempts}}}}}}}}}\n")
    return ("results/gda_decomposition.json", "--configfile", "config/config.yaml", f"{name}.yaml")


def _refusal(workdir, attempts):
    """What a dry run of the decomposition prints for an overlay holding these attempts (flow-style
    YAML), and its exit status."""
    from workflow_helpers import snakemake

    (workdir / "bad.yaml").write_text(f"downstream: {{experiments: {{gda_decomposition: {{attempts: {attempts}}}}}}}\n")
    res = snakemake(workdir, "--dry-run", "results/gda_decomposition.json", "--configfile", "config/config.yaml",
                    "bad.yaml", check=False)
    return res.returncode, res.stdout + res.stderr


def test_a_generator_attempt_samples_and_labels_from_its_own_generator(workdir):
    """attempts.<name>.generator: the generated row is trained again on scans from a generator with
    those keys laid over the generator section (here a longer run), sampled and pseudo-labelled
    beside the main ones; the main generator, its samples and the other rows are shared."""
    from workflow_helpers import snakemake

    (workdir / "long.yaml").write_text(
        "downstream: {experiments: {gda_decomposition: {backbones: [minkunet], "
        "attempts: {long: {generator: {training: {iterations: 1500}}}}}}}\n")
    args = ("results/gda_decomposition.json", "--configfile", "config/config.yaml", "long.yaml")
    jobs = _jobs(workdir, *args)
    assert jobs["train_generator"] == 1 and jobs["train_generator_attempt"] == 1
    assert jobs["sample_attempt"] == jobs["sample_domain"] >= 1  # the Vehicle shards holding N scans, twice
    assert jobs["train_study"] == 7 * 3 + 3
    out = snakemake(workdir, "--dry-run", "--printshellcmds", *args).stdout
    train = next(line for line in out.splitlines() if "omnilidar train-generator" in line and "attempt-long" in line)
    assert '"iterations": 1500' in train and "--preset full" in train and "--work-dir work/generator/attempt-long" in train
    main = next(line for line in out.splitlines() if "omnilidar train-generator" in line and "attempt-long" not in line)
    assert '"iterations": 1500' not in main
    tried = [line for line in out.splitlines()
             if "omnilidar train-segmentor" in line and "study-gda-vehicle-long" in line]
    assert len(tried) == 3 and all("--samples data/samples/attempt-long/Vehicle/shard_0" in line
                                   and "--pseudo-labels data/pseudo_labels/attempt-long/Vehicle/shard_0" in line
                                   and '"generator"' not in line for line in tried)
    plain = [line for line in out.splitlines() if "omnilidar train-segmentor" in line and "study-gda-vehicle48" in line]
    assert len(plain) == 3 and all("--samples data/samples/Vehicle/shard_0" in line for line in plain)
    assert "--checkpoint data/generator/attempt-long/model.pt" in out
    # The attempt may not move the shard layout its rows are read from.
    code, said = _refusal(workdir, "{long: {generator: {sampling: {scans_per_shard: 3}}}}")
    assert code != 0 and "attempts.long.generator may not change sampling" in said


def test_sdedit_attempts_start_from_the_domains_scans_and_share_a_generator_trained_alike(workdir):
    """Attempts that set generator.sampling.strength sample from the domain's training scans (the
    domains index is their input); attempts whose generators would train alike share one."""
    from workflow_helpers import snakemake

    args = _attempts_overlay(workdir, "edit", (
        "long: {generator: {training: {iterations: 1500}}}, "
        "long_edit50: {generator: {training: {iterations: 1500}, sampling: {strength: 0.5}}}, "
        "edit50: {generator: {sampling: {strength: 0.5}}}"))
    jobs = _jobs(workdir, *args)
    assert jobs["train_generator"] == 1 and jobs["train_generator_attempt"] == 1  # long and long_edit50 share it
    assert jobs["sample_attempt"] == 3 * jobs["sample_domain"]
    out = snakemake(workdir, "--dry-run", "--printshellcmds", *args).stdout
    samples = [line for line in out.splitlines() if "omnilidar sample " in line]
    by_dir = {line.split("--out ")[1].split()[0].rsplit("/", 2)[0]: line for line in samples}
    assert "--domains" not in by_dir["data/samples"] and "--domains" not in by_dir["data/samples/attempt-long"]
    for name, checkpoint in (("edit50", "full"), ("long_edit50", "attempt-long")):
        line = by_dir[f"data/samples/attempt-{name}"]
        assert "--domains data/domains/index.json" in line and '"strength": 0.5' in line
        assert f"--checkpoint data/generator/{checkpoint}/model.pt" in line
    result = next(line for line in out.splitlines() if "omnilidar gda-decomposition" in line)
    assert "--generator-iterations 300" in result and result.count("--attempt long_edit50=") == 3
    # The shipped sweep trains its longer generator once for all of its attempts.
    jobs = _jobs(workdir, "results/gda_decomposition.json", "--configfile", "config/config.yaml",
                 "config/strength_sweep.yaml")
    assert jobs["train_generator_attempt"] == 2 and jobs["train_study"] == (7 + 29) * 3
    assert jobs["carry_labels"] == 12 * jobs["sample_domain"]


def test_carried_label_attempts_train_on_their_sources_labels_not_the_labelers(workdir):
    """An SDEdit attempt with `labels: carried` labels its scans with carry-labels (no pseudo-label
    job) and trains on those; without strength < 1, or with another value, the config is refused."""
    from workflow_helpers import snakemake

    args = _attempts_overlay(workdir, "carried", (
        "edit50: {generator: {sampling: {strength: 0.5}}}, "
        "true50: {labels: carried, generator: {sampling: {strength: 0.5}}}"))
    out = snakemake(workdir, "--dry-run", "--printshellcmds", *args).stdout
    carry = [line for line in out.splitlines() if "omnilidar carry-labels " in line]
    pseudo = [line for line in out.splitlines() if "omnilidar pseudo-label " in line and "attempt-" in line]
    shards = sum("omnilidar sample " in line and "attempt-edit50/" in line for line in out.splitlines())
    assert len(carry) == shards > 0 and all("--samples data/samples/attempt-true50/" in c for c in carry)
    assert pseudo and not any("attempt-true50" in line for line in pseudo)
    runs = [line for line in out.splitlines() if "omnilidar train-segmentor" in line and "study-gda-" in line]
    true50 = [line for line in runs if "-true50" in line.split("--out ")[1]]
    assert len(true50) == 3 and all("--pseudo-labels data/carried_labels/attempt-true50/" in r for r in true50)
    assert all('"labels"' not in r for r in true50)  # not a training key
    for bad, why in (("{labels: carried, generator: {training: {iterations: 10}}}", "needs generator.sampling.strength < 1"),
                     ("{labels: truth, generator: {sampling: {strength: 0.5}}}", "expected one of labeler, carried"),
                     ("{generator: {sampling: {keep_source: [range]}}}", "keep_source copies channels")):
        code, said = _refusal(workdir, f"{{x: {bad}}}")
        assert code != 0 and why in said


def test_labeler_attempts_label_with_a_labeler_of_their_own(workdir):
    """An attempt with a `labeler` key trains its own labeler (shared by attempts that would train it
    alike), labels its scans (the main samples, or its own) with it, records its val scores in the
    result, and keeps the labeler's keys out of the students' settings; bad labeler keys and a
    labeler beside carried labels are refused at config time."""
    from workflow_helpers import snakemake

    args = _attempts_overlay(workdir, "robust", (
        "robust: {labeler: {augmentation: {range_jitter: 0.05}}}, "
        "robust_too: {labeler: {augmentation: {range_jitter: 0.05}}}, "
        "robust_edit50: {labeler: {augmentation: {range_jitter: 0.05}}, generator: {sampling: {strength: 0.5}}}"))
    jobs = _jobs(workdir, *args)
    assert jobs["train_labeler"] == jobs["train_labeler_attempt"] == jobs["evaluate_labeler_attempt"] == 1
    out = snakemake(workdir, "--dry-run", "--printshellcmds", *args).stdout
    lines = out.splitlines()
    own = next(line for line in lines if "omnilidar train-labeler" in line and "attempt-robust.pt" in line)
    assert '"range_jitter": 0.05' in own
    fixed = next(line for line in lines if "omnilidar train-labeler" in line and "semantickitti.pt" in line)
    assert '"range_jitter": 0' in fixed and '"range_jitter": 0.05' not in fixed
    pseudo = {line.split("--out ")[1].split()[0]: line for line in lines if "omnilidar pseudo-label --labeler" in line
              and "--samples" in line}
    for name, samples in (("robust", "data/samples/Vehicle/"), ("robust_too", "data/samples/Vehicle/"),
                          ("robust_edit50", "data/samples/attempt-robust_edit50/Vehicle/")):
        mine = [line for out_dir, line in pseudo.items() if out_dir.startswith(f"data/pseudo_labels/attempt-{name}/")]
        assert mine and all("--labeler data/labeler/attempt-robust.pt" in m and f"--samples {samples}" in m for m in mine)
    assert all("--labeler data/labeler/semantickitti.pt" in line for out_dir, line in pseudo.items()
               if not out_dir.startswith("data/pseudo_labels/attempt-"))
    runs = [line for line in lines if "omnilidar train-segmentor" in line and "study-gda-" in line]
    robust = [line for line in runs if "-robust48_" in line.split("--out ")[1]]
    assert len(robust) == 3 and all("--pseudo-labels data/pseudo_labels/attempt-robust/" in r for r in robust)
    assert not any('"range_jitter": 0.05' in r or '"labeler"' in r for r in runs)  # not a training key
    result = next(line for line in lines if "omnilidar gda-decomposition" in line and "--attempt " in line)
    assert all(f"--attempt-labeler {name}=data/labeler/attempt-robust.val.json" in result
               for name in ("robust", "robust_too", "robust_edit50"))
    # The shipped study: one generator and two labelers of their own for its fifteen attempts.
    jobs = _jobs(workdir, "results/gda_decomposition.json", "--configfile", "config/config.yaml",
                 "config/robust_labeler.yaml")
    assert jobs["train_generator_attempt"] == 1 and jobs["train_labeler_attempt"] == 2
    assert jobs["train_study"] == (7 + 15) * 3 and jobs["carry_labels"] == 3 * jobs["sample_domain"]
    for bad, why in (("{labels: carried, labeler: {batch_size: 1}, generator: {sampling: {strength: 0.5}}}",
                      "sets both labels: carried and a labeler of its own"),
                     ("{labeler: {augmentation: {range_jiter: 0.05}}}", "attempts.x.labeler"),
                     ("{labeler: {batch_size: 1}}, x1: {labeler: {batch_size: 1}}", "'x' and 'x1': run files name")):
        code, said = _refusal(workdir, f"{{x: {bad}}}")
        assert code != 0 and why in said


def test_weather_decomposition_reuses_the_real_rows_and_adds_generated_and_simulated_fog(workdir):
    """results/gda_decomposition_fog.json: the four real rows are the main study's runs scored on
    the fog corrupted sets; the generated row takes Fog samples, the simulated row the pool through
    the fog scene (built once)."""
    from workflow_helpers import snakemake

    jobs = _jobs(workdir, "results/gda_decomposition.json", "results/gda_decomposition_fog.json")
    # real, truth, pseudo, LaserMix, GDA vehicle, round trip (true, labeler); GDA fog, simulated fog
    assert jobs["train_study"] == (7 + 2) * 2 * 3
    assert jobs["evaluate_segmentor"] == 42 + 36 and jobs["simulate_pool"] == 1
    assert jobs["build_corrupted"] == 3  # fog at three severities, nothing else
    out = snakemake(workdir, "--dry-run", "--printshellcmds", "results/gda_decomposition_fog.json").stdout
    assert "--pool data/subsets/simulated/fog_1pct_pool48/pool.json --pool-source simulated" in out
    assert "--domains fog --max-generated 48" in out
    result = next(line for line in out.splitlines() if "omnilidar gda-decomposition" in line)
    assert "--evalset fog --domain fog" in result and "minkunet_1pct_study-truth48_seed0.fog.json" in result


def test_budget_study_trains_one_generator_per_budget_and_reuses_the_main_one(workdir):
    """results/gda_budget.json: a generator per budget (the main generator's own budget is the main
    generator), each sampled, pseudo-labelled, trained with every seed and scored against held-out
    real scans; supervised-only and pseudo-labelled real rows are the decomposition's runs."""
    from workflow_helpers import snakemake

    (workdir / "budget.yaml").write_text(
        "downstream: {experiments: {gda_budget: {iterations: [30, 300, 3000], metrics: [JSD, MMD]}}}\n")
    args = ("results/gda_budget.json", "--configfile", "config/config.yaml", "budget.yaml")
    jobs = _jobs(workdir, *args)
    assert jobs["train_generator"] == 1 and jobs["train_generator_attempt"] == 2  # 300 is the main generator
    assert jobs["budget_quality"] == 3 and jobs["gda_budget"] == 1 and "train_extractor" not in jobs
    assert jobs["train_study"] == (2 + 3) * 3  # supervised-only, pseudo-labelled real, three budgets; MinkUNet
    out = snakemake(workdir, "--dry-run", "--printshellcmds", *args).stdout
    train = [line for line in out.splitlines() if "omnilidar train-generator" in line]
    assert sorted(int(line.split('"iterations": ')[1].split(",")[0]) for line in train) == [30, 300, 3000]
    result = next(line for line in out.splitlines() if "omnilidar gda-budget" in line)
    assert "--budget 300=data/generator/full/model.pt=data/budget/quality_300.json" in result
    assert "--budget 30=data/generator/attempt-budget30/model.pt" in result
    assert result.count("--run 3000=") == 3 and "minkunet_1pct_study-gda-vehicle48_seed2" in result
    assert "study-gda-vehicle-budget3000" in result and "spvcnn_1pct" not in result
    quality = [line for line in out.splitlines() if "omnilidar sample-quality" in line]
    assert len(quality) == 3 and all("--metrics JSD MMD" in line for line in quality)
    assert any("--samples data/samples/attempt-budget30/Vehicle/shard_0" in line for line in quality)
