"""The domain stage in the workflow: DAG shape of the `domains` target, only the
needed sources per domain, and a tiny real run of one domain shard."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from ground_scenes import make_scene
from omnilidar.config import section_defaults
from omnilidar.domains.spec import domain_names
from omnilidar.io import semantickitti
from omnilidar.lidar.sensors import PRESETS
from workflow_helpers import copy_workflow, planned_jobs, snakemake, synthesized_shards


def _with_domain_stage(workdir):
    """Wire rules/domains.smk into the copy if the checkout does not yet."""
    snakefile = workdir / "Snakefile"
    text = snakefile.read_text()
    if "rules/domains.smk" not in text:
        text = text.replace('include: "rules/data.smk"\n', 'include: "rules/data.smk"\ninclude: "rules/domains.smk"\n')
        snakefile.write_text(text)
    schema = workdir / "workflow" / "schemas" / "config.schema.yaml"
    doc = yaml.safe_load(schema.read_text())
    if "domains" not in doc["properties"]:
        schema.write_text(schema.read_text().rstrip("\n") + "\n  domains:\n    $ref: domains.schema.yaml\n")
    return workdir


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return _with_domain_stage(copy_workflow(tmp_path_factory.mktemp("wf_domains")))


def test_domains_target_builds_every_shard_and_corrupted_set(workdir):
    jobs = planned_jobs(workdir, "domains")
    cfg = section_defaults("domains")
    shards = sum(cfg[name]["num_shards"] for name in domain_names(cfg))
    assert len(domain_names(cfg)) == 8
    assert jobs["build_domain"] == shards == 16
    assert jobs["build_corrupted"] == len(cfg["corrupted"]["corruptions"]) * len(cfg["corrupted"]["severities"]) == 12
    assert jobs["domains_index"] == 1 and jobs["domains"] == 1
    # Only the two sources the domains read are indexed.
    assert jobs["index_dataset"] == 2
    assert set(synthesized_shards(workdir, "domains")).isdisjoint({"kitti360", "nuscenes"})


def test_a_domain_needs_only_its_own_source(workdir):
    fog = planned_jobs(workdir, "data/domains/fog/shard_1")
    assert fog["build_domain"] == 1 and fog["index_dataset"] == 1
    assert "pi3det" not in synthesized_shards(workdir, "data/domains/fog/shard_1") and "build_corrupted" not in fog
    drone = planned_jobs(workdir, "data/domains/drone/shard_0")
    drone_shards = synthesized_shards(workdir, "data/domains/drone/shard_0")
    assert drone["build_domain"] == 1 and "semantickitti" not in drone_shards
    assert drone_shards["pi3det"] >= 1


def test_tiny_real_run_of_one_domain_shard(workdir, tmp_path):
    # A real (not synthesized) SemanticKITTI root with two train scans.
    root = tmp_path / "skitti"
    seq = root / "sequences" / "00"
    (seq / "velodyne").mkdir(parents=True)
    (seq / "labels").mkdir()
    kitti = PRESETS["kitti_hdl64e"]
    for i in range(2):
        scan = make_scene(kitti, np.random.default_rng(30 + i), azimuth_steps=256)
        semantickitti.write_scan(scan, seq / "velodyne" / f"{i:06d}.bin", seq / "labels" / f"{i:06d}.label")
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(yaml.safe_dump({
        "datasets": {"semantickitti": {"root": str(root)}},
        "domains": {"range_image": {"width": 256, "height": 64}, "fog": {"num_shards": 1, "max_scans": 2}},
        "generator": {"range_image": {"width": 256, "height": 64}},
    }))
    target = "data/domains/fog/shard_0"
    snakemake(workdir, target, "--configfile", str(cfg))
    shard = workdir / target
    side = json.loads((shard / "sidecar.json").read_text())
    assert [s["name"] for s in side["scans"]] == ["000000", "000001"]
    assert sorted(p.name for p in (shard / "range").iterdir()) == ["000000.npz", "000001.npz"]
    with np.load(shard / "range" / "000000.npz") as data:
        assert data["image"].shape == (2, 64, 256)
    log = (workdir / "logs" / "domains" / "fog_0.log").read_text()
    assert log.startswith("$ omnilidar build-domain fog")
    assert (workdir / "benchmarks" / "out" / "domains" / "fog_0.tsv").is_file()
    assert planned_jobs(workdir, target, "--configfile", str(cfg)) == {}  # nothing left to do


def test_domain_reports_run_on_synthetic_sweeps_unless_scans_are_listed(workdir, tmp_path):
    """Embedded default: the fidelity and trade-off reports read the SemanticKITTI index (the
    synthetic world's sweeps), a declared input; listed scan files replace it."""
    reports = ("results/domain_fidelity.json", "results/effects_tradeoff.json")
    jobs = planned_jobs(workdir, *reports)
    assert jobs["domain_fidelity"] == 1 and jobs["effects_tradeoff"] == 1
    assert jobs["index_dataset"] == 1 and synthesized_shards(workdir, *reports).get("semantickitti", 0) >= 1
    scans = []
    for i in range(2):
        scans.append(tmp_path / f"{i:06d}.bin")
        semantickitti.write_points(scans[-1], np.zeros((4, 4), np.float32))
    cfg = tmp_path / "listed.yaml"
    cfg.write_text(yaml.safe_dump({"domains": {"fidelity": {"scans": [str(p) for p in scans]}}}))
    jobs = planned_jobs(workdir, *reports, "--configfile", "config/config.yaml", str(cfg))
    assert jobs == {"domain_fidelity": 1, "effects_tradeoff": 1}


def test_domain_fidelity_reads_the_first_scans_of_the_index(tmp_path):
    from omnilidar.cli import main

    root = tmp_path / "skitti"
    seq = root / "sequences" / "00"
    (seq / "velodyne").mkdir(parents=True)
    (seq / "labels").mkdir()
    for i in range(3):
        scan = make_scene(PRESETS["kitti_hdl64e"], np.random.default_rng(40 + i), azimuth_steps=256)
        semantickitti.write_scan(scan, seq / "velodyne" / f"{i:06d}.bin", seq / "labels" / f"{i:06d}.label")
    index = tmp_path / "semantickitti.json"
    assert main(["index-dataset", "semantickitti", "--root", str(root), "--source", "synthetic",
                 "--out", str(index)]) == 0
    settings = {"fidelity": {"effects": ["beam_reduction"], "seeds": [0], "max_scans": 2}}
    out = tmp_path / "fidelity.json"
    rc = main(["domain-fidelity", "--settings", json.dumps(settings), "--seed", "0", "--out", str(out),
               "--figure", str(tmp_path / "fidelity.png"), "--index", str(index)])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert doc["data_source"] == {"semantickitti": {"root": str(root), "kind": "synthetic"}}
    assert [p.rsplit("/", 1)[-1] for p in doc["scans"]] == ["000000.bin", "000001.bin"]
