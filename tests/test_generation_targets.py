"""The generation targets end to end on a tiny untrained generator, and their workflow rules."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from omnilidar.cli import main
from omnilidar.config import section_defaults
from omnilidar.data.range_image import encode, project
from omnilidar.io.semantickitti import write_points
from omnilidar.metrics.extractors.weights import build_model, save_self_trained
from omnilidar.report.generation import metric_table, pareto_front, provenance_note

DOMAINS = ["Vehicle", "Beam32"]

# Every result names the datasets it used (omnilidar.data_source).
DATA_SOURCE = {"semantickitti": {"root": "/data/kitti", "kind": "real"},
               "pi3det": {"root": "data/synthetic/pi3det", "kind": "synthetic"}}
DATA_SOURCE_ARGS = ["--data-source", json.dumps(DATA_SOURCE)]


def tiny_generator_settings() -> dict:
    g = section_defaults("generator")
    g["range_image"].update(height=32, width=256)
    g["model"].update(base_channels=8, channel_multipliers=[1, 2], num_res_blocks=1, cross_attention_levels=[1],
                      cdfm_levels=[1], dafs_embed_dim=4)
    return g


@pytest.fixture(scope="module")
def fixture_dir(tmp_path_factory, synthetic_sweeps) -> Path:
    """Domains index with two full HDL-64E sweeps (Beam32 = every other row), a prompt cache,
    an untrained generator checkpoint, a self-trained-format FRID extractor, a KITTI-360
    style index and an effects_tradeoff.json."""
    from omnilidar.generator.text import CACHE_FORMAT
    from omnilidar.generator.checkpoint import CHECKPOINT_FORMAT
    from omnilidar.generator.unet import build_denoiser, range_image_spec

    root = tmp_path_factory.mktemp("gen_targets")
    g = tiny_generator_settings()
    spec = range_image_spec(g)
    imgs = []
    for name, scan in zip(("000000", "000001"), synthetic_sweeps):
        pts = scan.points
        write_points(root / f"{name}.bin", pts)
        proj = project(pts, spec)
        imgs.append(encode(proj.range_img, proj.intensity_img, spec))
    index = {"domains": {}}
    for k, dom in enumerate(DOMAINS):
        shard = root / "domains" / dom / "shard_0" / "range"
        shard.mkdir(parents=True)
        for i, img in enumerate(imgs * 2):
            img = img.copy()
            if dom == "Beam32":
                img[:, 1::2] = -1.0
            np.savez(shard / f"{i:06d}.npz", image=img)
        index["domains"][dom] = {"id": k, "name": dom.lower(), "num_scans": 4, "shards": [f"domains/{dom}/shard_0"]}
    (root / "index.json").write_text(json.dumps(index))

    dim, t = 8, 3
    gen = torch.Generator().manual_seed(0)
    cache = {"format": CACHE_FORMAT, "encoder": "test", "model": "test", "dim": dim, "max_tokens": t,
             "domains": {d: {"prompts": [f"{d} prompt"], "tokens": torch.randn(1, t, dim, generator=gen),
                             "mask": torch.ones(1, t, dtype=torch.bool)} for d in DOMAINS}}
    torch.save(cache, root / "prompts.pt")
    torch.manual_seed(0)
    den = build_denoiser(g, dim, len(DOMAINS))
    torch.save({"format": CHECKPOINT_FORMAT, "state_dict": den.state_dict(), "config": g, "domains": DOMAINS,
                "text": {"encoder": "test", "model": "test", "dim": dim}, "seed": 0}, root / "model.pt")

    arch = {"in_channels": 4, "depth": 21, "width": 4}
    save_self_trained(root / "frid.pt", "frid", arch, "feedbeef", build_model("frid", arch), {})
    arch = {"num_classes": 19}
    save_self_trained(root / "fpd.pt", "fpd", arch, "cafe", build_model("fpd", arch), {})
    (root / "kitti360.json").write_text(json.dumps({"splits": {"test": [
        {"points": str(root / "000000.bin"), "labels": None}, {"points": str(root / "000001.bin"), "labels": None}]}}))
    effects = {"effects": {"fog": {"primary_error": "err_fog_fraction", "rows": [
        {"knob": "samples", "value": v, "time_s": 0.01 * v, "errors": {"err_fog_fraction": 1.0 / v},
         "is_default": v == 4} for v in (1, 4, 16)]}}}
    (root / "effects.json").write_text(json.dumps(effects))
    return root


def _settings(**extra) -> str:
    s = {"scans_per_set": 2, "batch_size": 2, "sampler": "ddim", "steps": 1, **extra}
    return json.dumps(s)


def test_generation_quality_and_ablation(fixture_dir, capsys):
    r = fixture_dir
    out = r / "gq.json"
    rc = main(["generation-quality", *DATA_SOURCE_ARGS, "--domains", str(r / "index.json"), "--prompts", str(r / "prompts.pt"),
               "--full", str(r / "model.pt"), "--baseline", f"Vehicle={r / 'model.pt'}",
               "--weights", f"frid={r / 'frid.pt'}",
               "--settings", _settings(generation_quality={"metrics": ["FRID", "JSD", "MMD"]}),
               "--out", str(out), "--markdown", str(r / "gq.md"), "--figure", str(r / "gq.png")])
    assert rc == 0
    res = json.loads(out.read_text())
    for key in ("experiment", "config_hash", "code_hash", "data_source", "device", "seeds", "timings"):
        assert key in res
    assert res["data_source"] == DATA_SOURCE
    assert set(res["scores"]) == set(DOMAINS)
    vehicle = res["scores"]["Vehicle"]
    # same checkpoint and seeds for both methods -> identical samples and scores
    assert vehicle["OmniLiDAR"]["FRID"] == vehicle["single-domain (R2DM)"]["FRID"] >= 0
    assert "single-domain (R2DM)" not in res["scores"]["Beam32"]
    assert res["weights"]["FRID"] == "self-trained:feedbeef" and res["comparable_with_paper"]["FRID"] is False
    md = (r / "gq.md").read_text()
    assert "| Vehicle |" in md and "not with published numbers" in md
    assert (r / "gq.png").stat().st_size > 1000

    rc = main(["ablation-table", *DATA_SOURCE_ARGS, "--domains", str(r / "index.json"), "--prompts", str(r / "prompts.pt"),
               "--checkpoint", f"cdts={r / 'model.pt'}", "--checkpoint", f"full={r / 'model.pt'}",
               "--settings", _settings(ablation={"metrics": ["JSD", "MMD"]}),
               "--out", str(r / "abl.json"), "--markdown", str(r / "abl.md"), "--figure", str(r / "abl.png")])
    assert rc == 0
    abl = json.loads((r / "abl.json").read_text())
    assert abl["presets"] == ["cdts", "full"] and abl["mean"]["cdts"] == abl["mean"]["full"]
    assert "CDTS + CDFM + DAFS (OmniLiDAR)" in (r / "abl.md").read_text()


def test_kitti360_and_evidence(fixture_dir):
    r = fixture_dir
    rc = main(["kitti360-generation", *DATA_SOURCE_ARGS, "--index", str(r / "kitti360.json"), "--prompts", str(r / "prompts.pt"),
               "--full", str(r / "model.pt"), "--weights", f"fpd={r / 'fpd.pt'}",
               "--settings", _settings(kitti360={"metrics": ["FPD", "JSD", "MMD"]}),
               "--out", str(r / "k.json"), "--markdown", str(r / "k.md"), "--figure", str(r / "k.png")])
    assert rc == 0
    k = json.loads((r / "k.json").read_text())
    assert k["scores"]["OmniLiDAR"]["FPD"] > 0 and k["paper"]["R2DM"]["FRD"] == 179.43

    rc = main(["generator-evidence", *DATA_SOURCE_ARGS, "--domains", str(r / "index.json"), "--prompts", str(r / "prompts.pt"),
               "--checkpoint", str(r / "model.pt"), "--settings", _settings(evidence={"scans": 2}),
               "--out", str(r / "ev.json"), "--markdown", str(r / "ev.md"), "--figure", str(r / "ev.png")])
    assert rc == 0
    ev = json.loads((r / "ev.json").read_text())
    st = ev["domains"]["Beam32"]["statistics"]
    assert st["real"]["empty_row_fraction"] >= 0.5  # the real Beam32 set has every other row empty
    # the fixture checkpoint is the untrained initialisation itself: identical samples
    assert ev["domains"]["Vehicle"]["trained"]["JSD"] == ev["domains"]["Vehicle"]["untrained"]["JSD"]
    assert "| Beam32 |" in (r / "ev.md").read_text()


def test_sampler_tradeoff_one_run(fixture_dir):
    r = fixture_dir
    # A stand-in student: the untrained checkpoint marked as a one-step student (distillation
    # itself is tested in test_generator_distill); the study samples it with DDIM x 1.
    payload = torch.load(r / "model.pt", weights_only=True)
    payload["student"] = {"sampler": "ddim", "steps": 1, "teacher": str(r / "model.pt"), "teacher_steps": 2,
                          "rounds": 1}
    torch.save(payload, r / "student.pt")
    settings = _settings(tradeoff={"samplers": {"ddim": [1, 2], "dpmpp_2m": [1], "unipc_karras": [2]}, "scans": 4,
                                   "seed_groups": 2, "student": True, "domains": ["Vehicle"],
                                   "feature_metrics": ["FRID"]})
    args = ["sampler-tradeoff", *DATA_SOURCE_ARGS, "--domains", str(r / "index.json"), "--prompts", str(r / "prompts.pt"),
            "--checkpoint", str(r / "model.pt"), "--weights", f"frid={r / 'frid.pt'}",
            "--weights", f"fpd={r / 'fpd.pt'}", "--effects", str(r / "effects.json"),
            "--settings", settings, "--out", str(r / "t.json"), "--figure", str(r / "t.png")]
    assert main(args) == 2 and not (r / "t.json").exists()  # the student is asked for but not given
    assert main([*args, "--student", str(r / "student.pt"), "--default-sampler", "ddim:2"]) == 0
    t = json.loads((r / "t.json").read_text())
    assert [(p["sampler"], p["steps"]) for p in t["points"]] == [
        ("ddim", 1), ("ddim", 2), ("dpmpp_2m", 1), ("unipc_karras", 2), ("student", 1)]
    assert all(p["seconds_per_scan"] > 0 for p in t["points"])
    assert any(p["pareto"]["JSD"] for p in t["points"]) and "JSD" in t["recommended"]
    vehicle = t["points"][0]["per_domain"]["Vehicle"]
    assert set(vehicle) >= {"JSD", "MMD", "FRID", "JSD_std", "FRID_groups", "set_seconds_per_scan"}
    assert vehicle["scans_per_group"] == 2 and len(vehicle["FRID_groups"]) == 2
    assert vehicle["JSD"] == pytest.approx(np.mean(vehicle["JSD_groups"]))
    # Best solver per budget of network evaluations, among every setting of that budget.
    assert set(t["best_per_budget"]) == {"1", "2"} and t["best_per_budget"]["2"]["JSD"]["candidates"] == 2
    # The one-step student and DDIM x 1 sample the same untrained network the same way.
    assert t["points"][-1]["mean_JSD"] == pytest.approx(t["points"][0]["mean_JSD"])
    # The study names the student it scored, beyond the study's own settings.
    assert t["student"]["checkpoint"] == str(r / "student.pt") and t["student"]["steps"] == 1
    assert t["student"]["teacher_steps"] == 2 and t["student"]["seed"] == payload["seed"]
    check = t["student_check"]
    assert check["decided_by"] == ["JSD", "MMD"] and set(check["metrics"]) == {"JSD", "MMD", "FRID"}
    jsd = check["metrics"]["JSD"]
    best = min((p for p in t["points"][:-1]), key=lambda p: p["mean_JSD"])
    assert jsd["teacher_best"] == {"sampler": best["sampler"], "steps": best["steps"]}
    row = jsd["per_domain"]["Vehicle"]
    assert row["excess"] == pytest.approx(row["student"] - row["teacher"]) and row["held"] == (row["excess"] <= 2 * row["spread"])
    assert check["held"] == all(not check["metrics"][m]["missed"] for m in ("JSD", "MMD"))
    assert check["default_sampler"]["steps"] == 2 and check["speedup_over_default"] > 0
    settings_check = t["teacher_settings_check"]
    assert list(settings_check) == ["ddim x 1", "ddim x 2", "dpmpp_2m x 1", "unipc_karras x 2"]
    best_jsd = f"{jsd['teacher_best']['sampler']} x {jsd['teacher_best']['steps']}"
    assert settings_check[best_jsd]["JSD"] == {"held": 1, "of": 1, "missed": {}}  # the best holds itself
    assert t["effects"][0]["name"] == "fog:samples" and t["downstream"] == []  # no GDA curve given
    assert (r / "t.png").stat().st_size > 1000


def test_the_study_times_every_setting_side_by_side_not_by_its_sets_recorded_time(fixture_dir, tmp_path):
    """A set's shards may have been sampled in another run under another load: the study keeps what
    they recorded beside, and times every setting itself in one job (seconds_per_scan)."""
    r = fixture_dir
    gen = json.loads(json.dumps(torch.load(r / "model.pt", weights_only=True)["config"]))
    gen["sampling"].update(sampler="ddim", steps=1, batch_size=2, scans_per_shard=4, device="cpu")
    shard = tmp_path / "Vehicle" / "shard_0"
    assert main(["sample", "--checkpoint", str(r / "model.pt"), "--prompts", str(r / "prompts.pt"), "--domain", "Vehicle",
                 "--shard", "0", "--settings", json.dumps(gen), "--seed", "0", "--out", str(shard)]) == 0
    timing = json.loads((shard / "timing.json").read_text())
    (shard / "timing.json").write_text(json.dumps({**timing, "seconds": 1000.0 * timing["scans"]}))  # a slow neighbour
    settings = _settings(tradeoff={"samplers": {"ddim": [1, 2]}, "scans": 4, "seed_groups": 2, "domains": ["Vehicle"],
                                   "feature_metrics": ["FRID"], "timing": {"scans": 1, "repeats": 2}})
    assert main(["sampler-tradeoff", *DATA_SOURCE_ARGS, "--domains", str(r / "index.json"), "--prompts",
                 str(r / "prompts.pt"), "--checkpoint", str(r / "model.pt"), "--weights", f"frid={r / 'frid.pt'}",
                 "--samples", f"ddim-1/Vehicle={shard}", "--settings", settings, "--out", str(tmp_path / "t.json"),
                 "--figure", str(tmp_path / "t.png")]) == 0
    t = json.loads((tmp_path / "t.json").read_text())
    from_shard, sampled_here = t["points"]
    assert from_shard["set_seconds_per_scan"] == pytest.approx(1000.0)
    assert from_shard["per_domain"]["Vehicle"]["set_seconds_per_scan"] == pytest.approx(1000.0)
    assert 0 < from_shard["seconds_per_scan"] < 100 and 0 < sampled_here["seconds_per_scan"] < 100
    assert "side by side" in t["device_note"]
    bad = _settings(tradeoff={"samplers": {"ddim": [1]}, "timing": {"repeats": 0}})
    assert main(["sampler-tradeoff", *DATA_SOURCE_ARGS, "--domains", str(r / "index.json"), "--prompts",
                 str(r / "prompts.pt"), "--checkpoint", str(r / "model.pt"), "--settings", bad,
                 "--out", str(tmp_path / "bad.json"), "--figure", str(tmp_path / "bad.png")]) == 2
    assert not (tmp_path / "bad.json").exists()


def _domains_tree(root: Path, images: dict[str, list[np.ndarray]], dataset: str, split: str) -> Path:
    """A domains index over ``images`` ({domain: [(2, H, W)]}) whose shards say where they come from."""
    index = {"domains": {}}
    for k, (dom, imgs) in enumerate(images.items()):
        shard = root / dom / "shard_0"
        (shard / "range").mkdir(parents=True)
        for i, img in enumerate(imgs):
            np.savez(shard / "range" / f"{i:06d}.npz", image=img)
        (shard / "sidecar.json").write_text(json.dumps({"dataset": dataset, "split": split}))
        index["domains"][dom] = {"id": k, "name": dom.lower(), "num_scans": len(imgs), "shards": [f"{dom}/shard_0"]}
    (root / "index.json").write_text(json.dumps(index))
    return root / "index.json"


def test_sampler_tradeoff_scores_against_the_reference_scans_and_says_whether_they_are_held_out(fixture_dir, tmp_path):
    """--reference gives the real scans (a held-out set), --domains stays the training scans: the
    scores change with the reference alone, and the result names both sources; a reference from the
    training split itself is not called held out."""
    from omnilidar.generator.data import load_range_image, read_domains_index

    r = fixture_dir
    train_imgs = [load_range_image(f) for f in read_domains_index(r / "index.json")["Vehicle"]["files"]]
    held = [img.copy() for img in train_imgs]
    for img in held:  # other scenes: the far half of every row gone
        img[:, :, : img.shape[2] // 2] = -1.0
    training = _domains_tree(tmp_path / "train", {"Vehicle": train_imgs}, "semantickitti", "train")
    heldout = _domains_tree(tmp_path / "heldout", {"Vehicle": held}, "semantickitti", "val")
    same_split = _domains_tree(tmp_path / "same", {"Vehicle": held}, "semantickitti", "train")
    settings = _settings(tradeoff={"samplers": {"ddim": [1]}, "scans": 2, "seed_groups": 1, "student": False,
                                   "domains": ["Vehicle"], "feature_metrics": ["FRID"]})

    def study(name, *reference):
        out = tmp_path / f"{name}.json"
        assert main(["sampler-tradeoff", *DATA_SOURCE_ARGS, "--domains", str(training), *reference,
                     "--prompts", str(r / "prompts.pt"), "--checkpoint", str(r / "model.pt"),
                     "--weights", f"frid={r / 'frid.pt'}",
                     "--settings", settings, "--out", str(out), "--figure", str(tmp_path / f"{name}.png")]) == 0
        return json.loads(out.read_text())

    own, held_out, same = study("own"), study("held", "--reference", str(heldout)), study("same", "--reference", str(same_split))
    assert own["reference"] == {"index": str(training), "held_out": False, "sources": {"Vehicle": "semantickitti train"},
                                "training_sources": {"Vehicle": "semantickitti train"}}
    assert held_out["reference"]["held_out"] and held_out["reference"]["sources"] == {"Vehicle": "semantickitti val"}
    assert not same["reference"]["held_out"]
    # The same generated scans (same seed), other real scans: other scores.
    assert held_out["points"][0]["mean_JSD"] != pytest.approx(own["points"][0]["mean_JSD"])
    assert same["points"][0]["mean_JSD"] == pytest.approx(held_out["points"][0]["mean_JSD"])
    from omnilidar.report.readme import reference_phrase

    assert "2 held-out real scans per domain (semantickitti val)" in reference_phrase(held_out)
    assert "training scans" in reference_phrase(same) and "training scans" in reference_phrase({"real_scans": 8})
    assert held_out["real_scans_per_domain"] == {"Vehicle": 2}
    # A held-out set with fewer scans than the study asks for is scored on what it has, and says so.
    fewer = study("fewer", "--reference", str(_domains_tree(tmp_path / "one", {"Vehicle": held[:1]}, "semantickitti", "val")))
    assert fewer["real_scans_per_domain"] == {"Vehicle": 1}
    assert "scored against 2 (Vehicle 1) held-out real scans per domain" in reference_phrase(fewer)


def test_every_teacher_setting_is_held_to_the_best_by_the_student_s_rule():
    from omnilidar.commands.sampler_tradeoff import teacher_settings_check

    def point(sampler, steps, jsd):
        return {"sampler": sampler, "steps": steps, "mean_JSD": jsd, "mean_MMD": None,
                "per_domain": {"Drone": {"JSD": jsd, "JSD_std": 0.006}}}

    points = [point("dpmpp_2m", 20, 0.49), point("ddim", 16, 0.51), point("ddim", 64, 0.495), point("student", 1, 0.5)]
    check = teacher_settings_check(points, ["JSD", "MMD"])
    assert list(check) == ["dpmpp_2m x 20", "ddim x 16", "ddim x 64"]  # the student is not the teacher's
    # two standard deviations of the difference: 2 * hypot(0.006, 0.006) = 0.017 < 0.02
    assert check["ddim x 16"]["JSD"]["held"] == 0 and check["ddim x 16"]["JSD"]["missed"] == {"Drone": pytest.approx(0.02)}
    assert check["ddim x 64"]["JSD"] == {"held": 1, "of": 1, "missed": {}}
    assert check["dpmpp_2m x 20"]["JSD"]["missed"] == {} and "MMD" not in check["ddim x 16"]  # no MMD scored


def test_report_helpers():
    assert pareto_front([1, 2, 3, 4], [5, 3, 4, 1]) == [True, True, False, True]
    assert pareto_front([1, 1], [2, 2]) == [True, True]  # ties dominate nothing
    md = metric_table({"Fog": {"a": {"JSD": 0.2, "MMD_1e4": 3.0}, "b": {"JSD": 0.1, "MMD_1e4": None}}},
                      ["JSD", "MMD"], ["a", "b"])
    assert "| Fog | 0.200 | **0.100** | **3.000** | n/a |" in md
    assert "self-trained" in provenance_note({"FRD": "self-trained:x"}, {"FRD": False})
    assert "self-trained" not in provenance_note({"FRD": "official:y"}, {"FRD": True})


def test_workflow_plans_the_evaluation_targets(tmp_path):
    from tests.workflow_helpers import copy_workflow, planned_jobs

    (tmp_path / "wf").mkdir()
    work = copy_workflow(tmp_path / "wf")
    snake = work / "Snakefile"
    text = snake.read_text()
    missing = "".join(f'include: "rules/{f}.smk"\n' for f in ("domains", "generator", "evaluation")
                      if f"rules/{f}.smk" not in text)
    snake.write_text(text.replace("\n\nrule all:", f"\n{missing}\n\nrule all:", 1))
    schema = work / "workflow" / "schemas" / "config.schema.yaml"
    s = schema.read_text()
    for sec in ("domains", "generator", "evaluation"):
        if f"{sec}.schema.yaml" not in s:
            s += f"  {sec}:\n    $ref: {sec}.schema.yaml\n"
    schema.write_text(s)
    jobs = planned_jobs(work, "results/generation_quality.json", "results/tradeoff.json",
                        "results/generator_evidence.json", "results/kitti360_generation.json", "results/ablation.json")
    assert jobs["generation_quality"] == 1 and jobs["sampler_tradeoff"] == 1 and jobs["generator_evidence"] == 1
    assert jobs["build_heldout_domain"] == 8 and jobs["heldout_domains_index"] == 1  # the study's real scans
    assert jobs["train_single_domain"] == 8  # one R2DM-equivalent baseline per domain
    assert jobs["train_extractor"] == 5  # every feature metric self-trained by default
    assert jobs["train_generator"] == 6  # the six ablation presets (full among them)


def test_single_domain_baselines_train_as_long_as_the_full_model_unless_told(tmp_path):
    """Paper protocol by default (baseline steps = generator.training.iterations); an explicit
    evaluation.generation_quality.baseline_iterations overrides it."""
    import re

    import yaml

    from tests.workflow_helpers import copy_workflow, snakemake

    work = copy_workflow(tmp_path)
    full = section_defaults("generator")["training"]["iterations"]  # config.yaml keeps the default
    assert "training" not in yaml.safe_load((work / "config" / "config.yaml").read_text()).get("generator", {})
    (work / "short.yaml").write_text("evaluation: {generation_quality: {baseline_iterations: 7}}\n")

    def baseline_iterations(*args):
        out = snakemake(work, "--dry-run", "--printshellcmds", "--forceall", "data/generator_single/Fog/model.pt", *args)
        match = re.search(r"--preset single_domain --settings '(\{.*?\})' ", out.stdout)
        training = json.loads(match.group(1))["training"]
        assert training["single_domain"] == "Fog"
        return training["iterations"]

    assert baseline_iterations() == full
    assert baseline_iterations("--configfile", "config/config.yaml", "short.yaml") == 7


def test_the_sampler_study_scores_against_held_out_sets_built_on_each_domain_s_heldout_split(tmp_path):
    """Each domain's held-out set is its scene spec on its heldout_split in one shard; the training
    builds do not read heldout_split; reference: training scores against the training index and
    builds no held-out set; a held-out split equal to the training split is a config error."""
    import re

    from tests.workflow_helpers import copy_workflow, planned_jobs, snakemake

    work = copy_workflow(tmp_path)
    out = snakemake(work, "--dry-run", "--printshellcmds", "--forceall", "results/tradeoff.json").stdout
    builds = re.findall(r"omnilidar build-domain (\w+) .*?--num-shards (\d+) --settings '(\{.*?\})' .*?--out (\S+)", out)
    heldout = {name: (n, json.loads(cfg)[name]) for name, n, cfg, dest in builds if "domains_heldout" in dest}
    training = {name: json.loads(cfg)[name] for name, n, cfg, dest in builds if "domains_heldout" not in dest}
    assert set(heldout) == set(training) == {"vehicle", "snow", "fog", "rain", "wet_ground", "beam32", "drone", "quadruped"}
    assert heldout["drone"][0] == "1" and heldout["drone"][1]["split"] == "drone_val" and heldout["fog"][1]["split"] == "val"
    assert heldout["fog"][1]["effects"] == training["fog"]["effects"] and training["fog"]["split"] == "train"
    assert not any("heldout_split" in entry for entry in training.values())
    study = re.search(r"omnilidar sampler-tradeoff --domains (\S+) --reference (\S+) ", out)
    assert study.groups() == ("data/domains/index.json", "data/domains_heldout/index.json")
    (work / "own.yaml").write_text("evaluation: {tradeoff: {reference: training}}\n")
    own = ("--configfile", "config/config.yaml", "own.yaml")
    assert "--reference data/domains/index.json" in snakemake(work, "--dry-run", "--printshellcmds", "--forceall",
                                                              "results/tradeoff.json", *own).stdout
    assert "build_heldout_domain" not in planned_jobs(work, "--forceall", "results/tradeoff.json", *own)
    (work / "same.yaml").write_text("domains: {fog: {heldout_split: train}}\n")
    bad = snakemake(work, "--dry-run", "results/tradeoff.json", "--configfile", "config/config.yaml", "same.yaml", check=False)
    assert bad.returncode != 0 and "domains.fog.heldout_split" in bad.stdout + bad.stderr


def test_generation_quality_reads_sample_shards_as_it_would_sample(fixture_dir, tmp_path):
    """The workflow passes the sets as `omnilidar sample` shards: same scans, same scores."""
    r = fixture_dir
    gen = json.loads(json.dumps(torch.load(r / "model.pt", weights_only=True)["config"]))
    gen["sampling"].update(sampler="ddim", steps=1, batch_size=2, scans_per_shard=2, device="cpu")
    args = ["--domains", str(r / "index.json"), "--prompts", str(r / "prompts.pt"), "--full", str(r / "model.pt"),
            "--weights", f"frid={r / 'frid.pt'}",
            "--settings", _settings(generation_quality={"metrics": ["FRID", "JSD", "MMD"]})]
    sets = []
    for dom in DOMAINS:
        shard = tmp_path / dom / "shard_0"
        assert main(["sample", "--checkpoint", str(r / "model.pt"), "--prompts", str(r / "prompts.pt"),
                     "--domain", dom, "--shard", "0", "--settings", json.dumps(gen), "--seed", "0",
                     "--out", str(shard)]) == 0
        sets += ["--samples", f"full/{dom}={shard}"]
    results = {}
    for name, extra in (("sampled", []), ("shards", sets)):
        out = tmp_path / f"{name}.json"
        assert main(["generation-quality", *DATA_SOURCE_ARGS, *args, *extra, "--seed", "0", "--out", str(out),
                     "--markdown", str(tmp_path / f"{name}.md"), "--figure", str(tmp_path / f"{name}.png")]) == 0
        results[name] = json.loads(out.read_text())["scores"]
    for dom in DOMAINS:
        a, b = results["sampled"][dom]["OmniLiDAR"], results["shards"][dom]["OmniLiDAR"]
        for metric in ("FRID", "JSD", "MMD_1e4"):
            assert a[metric] == pytest.approx(b[metric], rel=1e-5), (dom, metric)
    # A set with fewer scans than asked for is one clear error.
    bad = tmp_path / "bad.json"
    assert main(["generation-quality", *DATA_SOURCE_ARGS, *args, "--samples", f"full/{DOMAINS[0]}={tmp_path / 'nowhere'}", "--seed", "0",
                 "--out", str(bad), "--markdown", str(tmp_path / "b.md"), "--figure", str(tmp_path / "b.png")]) == 2
    assert not bad.exists()
