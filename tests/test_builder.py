"""Domain builder: only what a scene calls for, exact regeneration from the sidecar,
results independent of sharding, and the shard layout the generator reads."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ground_scenes import make_scene
from omnilidar.config import section_defaults
from omnilidar.data.index import build_index, write_index
from omnilidar.domains import builder as B
from omnilidar.domains import ground as G
from omnilidar.domains.effects import snow as S
from omnilidar.domains.effects import wet_ground as W
from omnilidar.domains.effects.base import WEATHER_RETURN_LABEL
from omnilidar.domains.index import domains_index
from omnilidar.domains.spec import EffectSpec, SceneSpec, domains_from_settings, get_domain
from omnilidar.errors import InputError
from omnilidar.generator.data import load_range_image, read_domains_index
from omnilidar.io import semantickitti
from omnilidar.lidar.sensors import PRESETS

KITTI = PRESETS["kitti_hdl64e"]
ALL_WEATHER = [("wet_ground", ["light", "moderate", "heavy"]), ("fog", ["light", "moderate", "heavy"]),
               ("snow", ["heavy"]), ("rain", ["moderate", "heavy"])]


def scene_spec(*items) -> SceneSpec:
    return SceneSpec(tuple(EffectSpec(name, tuple(sev)) for name, sev in items))


def same_scan(a, b) -> bool:
    return (np.array_equal(a.points, b.points) and np.array_equal(a.semantic, b.semantic)
            and np.array_equal(a.instance, b.instance) and np.array_equal(a.ring, b.ring)
            and np.array_equal(a.boxes.boxes, b.boxes.boxes))


@pytest.fixture(scope="module")
def world():
    """A ray-cast street with ground-truth labels (road/sidewalk = ground), and its
    estimated ground mask."""
    scan = make_scene(KITTI, np.random.default_rng(3), azimuth_steps=384)
    return scan, G.ground_truth_mask(scan.semantic), G.estimate_ground(scan, KITTI)


def test_empty_spec_returns_the_input_object(world):
    scan = world[0]
    out, record = B.build_scan(scan, SceneSpec(), KITTI, np.random.default_rng(0))
    assert out is scan
    assert record == {"effects": [], "ground_estimated": False}


def test_zero_severity_returns_the_input_bit_for_bit(world, monkeypatch):
    scan = world[0]
    monkeypatch.setattr(G, "estimate_ground", lambda *a, **k: pytest.fail("no effect runs, so no ground"))
    spec = scene_spec(*[(name, ["none"]) for name in ("fog", "snow", "rain", "wet_ground", "beam_reduction")])
    out, record = B.build_scan(scan, spec, KITTI, np.random.default_rng(0))
    assert out is scan and all(s["params"] is None for s in record["effects"])
    # Zero-valued physical parameters: every effect hands back its input.
    zero = {"fog": {"alpha": 0.0, "beta": 0.2, "range_jitter": 1.0}, "snow": {"snowfall_rate": 0.0,
            "terminal_velocity": 1.6}, "rain": {"rate_mm_h": 0.0}, "beam_reduction": {"keep_every": 1},
            "beam_missing": {"drop_fraction": 0.0}}
    for name, params in zero.items():
        record = {"effects": [{"name": name, "params": params, "seed": 7, "fidelity": {}}]}
        assert B.rebuild_scan(scan, record, KITTI) is scan, name
    monkeypatch.undo()
    record = {"effects": [{"name": "wet_ground", "params": {"water_height_mm": 0.0, "noise_floor": 0.7},
                           "seed": 7, "fidelity": {}}]}
    assert same_scan(B.rebuild_scan(scan, record, KITTI), scan)


@pytest.mark.parametrize("name", ["fog", "snow", "rain", "beam_reduction", "beam_missing"])
def test_effects_without_ground_never_estimate_it(world, monkeypatch, name):
    def forbidden(*args, **kwargs):
        raise AssertionError(f"{name}-only scene estimated ground")

    monkeypatch.setattr(G, "estimate_ground", forbidden)
    severities = ["half"] if name == "beam_reduction" else ["heavy"]
    out, record = B.build_scan(world[0], scene_spec((name, severities)), KITTI, np.random.default_rng(1))
    assert record["ground_estimated"] is False
    assert out is not world[0]


def test_ground_is_estimated_once_for_a_chain_that_needs_it(world, monkeypatch):
    calls = []
    real = G.estimate_ground
    monkeypatch.setattr(G, "estimate_ground", lambda *a, **k: calls.append(1) or real(*a, **k))
    _, record = B.build_scan(world[0], scene_spec(*ALL_WEATHER), KITTI, np.random.default_rng(2))
    assert calls == [1] and record["ground_estimated"] is True


def test_wet_ground_changes_only_ground_beyond_the_estimators_error(world):
    scan, truth, est = world
    out, record = B.build_scan(scan, scene_spec(("wet_ground", ["heavy"])), KITTI, np.random.default_rng(4))
    step = record["effects"][0]
    # The builder handed the effect the estimated ground: same result as applying it by hand.
    ref, info = W.apply(scan, step["params"], KITTI, np.random.default_rng(step["seed"]), ground=est, return_info=True)
    assert same_scan(out, ref)
    affected = info["lost"] | info["changed"]
    assert affected.sum() > 0.05 * truth.sum()
    assert not (affected & ~est).any()  # only estimated ground is touched
    precision = (est & truth).sum() / est.sum()
    assert precision > 0.9
    # Non-ground points touched: at most the estimator's own false positives.
    assert (affected & ~truth).sum() / affected.sum() <= (1 - precision) + 0.02
    kept = ~info["lost"]
    untouched = ~info["changed"][kept]
    assert np.array_equal(out.points[untouched], scan.points[kept][untouched])
    assert np.array_equal(out.semantic, scan.semantic[kept])  # order kept, labels follow


def test_snow_changes_only_beams_that_hit_a_flake(world, monkeypatch):
    scan = world[0]
    flakes = []  # the flake field the effect draws: (beam index, range, occluded fraction)
    real = S.sample_flakes
    monkeypatch.setattr(S, "sample_flakes", lambda *a, **k: flakes.append(real(*a, **k)) or flakes[-1])
    out, record = B.build_scan(scan, scene_spec(("snow", ["heavy"])), KITTI, np.random.default_rng(5))
    step = record["effects"][0]
    ref, info = S.apply(scan, step["params"], KITTI, np.random.default_rng(step["seed"]), return_info=True)
    assert same_scan(out, ref) and len(flakes) == 2
    assert np.array_equal(flakes[0][0], flakes[1][0])
    hit = np.zeros(len(scan), bool)
    hit[flakes[0][0]] = True
    affected = info["lost"] | info["changed"]
    assert affected.any() and not (affected & ~hit).any()
    kept = ~info["lost"]
    untouched = ~affected[kept]
    assert np.array_equal(out.points[untouched], scan.points[kept][untouched])
    assert np.all(out.semantic[info["weather"]] == WEATHER_RETURN_LABEL)
    assert np.all(out.instance[info["weather"]] == 0)


def test_record_regenerates_the_scan_bit_for_bit(world):
    scan = world[0]
    spec = scene_spec(*ALL_WEATHER, ("beam_reduction", ["half"]))
    out, record = B.build_scan(scan, spec, KITTI, B.scan_rng(0, 5, 17))
    record = json.loads(json.dumps(record))  # through the sidecar
    again = B.rebuild_scan(scan, record, KITTI)
    assert same_scan(out, again) and len(out) < len(scan)
    assert [s["name"] for s in record["effects"]] == ["wet_ground", "fog", "snow", "rain", "beam_reduction"]
    assert out.semantic is not None and len(out.semantic) == len(out)
    # Another seed draws other severities / parameters.
    _, record2 = B.build_scan(scan, spec, KITTI, B.scan_rng(0, 5, 18))
    assert record2["effects"] != record["effects"]


def test_severity_is_uniform_over_the_list():
    effect = EffectSpec("fog", ("light", "moderate", "heavy"))
    rng = np.random.default_rng(0)
    draws = [effect.draw_severity(rng) for _ in range(3000)]
    for name in effect.severities:
        assert abs(draws.count(name) / 3000 - 1 / 3) < 0.04
    assert EffectSpec("fog", ("heavy",)).draw_severity(rng) == "heavy"


def test_bad_specs_are_input_errors():
    with pytest.raises(InputError, match="unknown effect"):
        EffectSpec("hail", ("light",))
    with pytest.raises(InputError, match="unknown severity"):
        EffectSpec("fog", ("extreme",))
    with pytest.raises(InputError, match="fidelity"):
        EffectSpec("fog", ("light",), {"samples": 3})
    settings = section_defaults("domains")
    with pytest.raises(InputError, match="unknown domain 'mist'"):
        get_domain(settings, "mist")
    settings["fog"]["id"] = 1  # snow's id
    with pytest.raises(InputError, match="id 1"):
        domains_from_settings(settings)


def test_default_domains_are_the_eight_paper_domains():
    specs = domains_from_settings(section_defaults("domains"))
    assert list(specs) == ["vehicle", "snow", "fog", "rain", "wet_ground", "beam32", "drone", "quadruped"]
    assert sorted(s.id for s in specs.values()) == list(range(8))
    assert [s.scene.needs_ground for s in specs.values()] == [False, False, False, False, True, False, False, False]
    assert specs["vehicle"].scene.effects == () and specs["drone"].dataset == "pi3det"


# ------------------------------------------------------------------ shards on disk


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory):
    """A SemanticKITTI root with three ray-cast scans in train sequence 00, and its index."""
    root = tmp_path_factory.mktemp("skitti")
    for i in range(3):
        scan = make_scene(KITTI, np.random.default_rng(10 + i), azimuth_steps=256)
        seq = root / "sequences" / "00"
        (seq / "velodyne").mkdir(parents=True, exist_ok=True)
        (seq / "labels").mkdir(exist_ok=True)
        semantickitti.write_scan(scan, seq / "velodyne" / f"{i:06d}.bin", seq / "labels" / f"{i:06d}.label")
    index = root / "index.json"
    write_index(build_index("semantickitti", root), index)
    return root, index


def _files(shard_dirs):
    out = {}
    for d in shard_dirs:
        for p in sorted(Path(d).rglob("*")):
            if p.is_file() and p.name not in ("sidecar.json", "MANIFEST.sha256"):  # per-shard metadata
                out[str(p.relative_to(d))] = p.read_bytes()
    return out


def test_shards_do_not_change_the_result(tiny_root, tmp_path):
    _, index = tiny_root
    settings = section_defaults("domains")
    settings["range_image"]["width"] = 256
    settings["wet_ground"].update(max_scans=None, effects=[{"name": "wet_ground", "severities": ["light", "heavy"]},
                                                           {"name": "fog", "severities": ["heavy"]}])
    domain = get_domain(settings, "wet_ground")
    B.build_domain_shard(domain, index, 0, 1, settings, 3, tmp_path / "one", progress=False)
    two = [tmp_path / f"two_{k}" for k in range(2)]
    for k, d in enumerate(two):
        B.build_domain_shard(domain, index, k, 2, settings, 3, d, progress=False)
    single, split = _files([tmp_path / "one"]), _files(two)
    assert sorted(single) == sorted(split) and len(single) == 9  # 3 x (range, velodyne, labels)
    assert all(single[k] == split[k] for k in single)
    side = B.read_sidecar(tmp_path / "one")
    parts = [B.read_sidecar(d)["scans"] for d in two]
    assert sorted([s["index"] for p in parts for s in p]) == [0, 1, 2]
    assert {s["index"]: s["effects"] for p in parts for s in p} == {s["index"]: s["effects"] for s in side["scans"]}


def test_shard_layout_reads_back_and_regenerates(tiny_root, tmp_path):
    root, index = tiny_root
    settings = section_defaults("domains")
    settings["range_image"].update(width=256, height=None)  # one row per beam
    settings["beam32"]["max_scans"] = 2
    settings["fog"]["max_scans"] = 2
    for name in ("fog", "beam32"):
        B.build_domain_shard(get_domain(settings, name), index, 0, 1, settings, 0, tmp_path / name / "shard_0",
                             progress=False)
    shard = tmp_path / "fog" / "shard_0"
    side = B.read_sidecar(shard)
    assert side["label"] == "Fog" and side["range_image"]["height"] == 64 and len(side["scans"]) == 2
    for rec in side["scans"]:
        image = load_range_image(shard / "range" / f"{rec['name']}.npz", (64, 256))
        assert image.dtype == np.float32 and (image > -1).any()
        points = semantickitti.read_points(shard / "velodyne" / f"{rec['name']}.bin")
        sem, _ = semantickitti.read_label(shard / "labels" / f"{rec['name']}.label", len(points))
        assert rec["num_points_out"] == len(points) and rec["effects"][0]["severity"] in ("light", "moderate", "heavy")
        source = semantickitti.read_scan(rec["source"], rec["source_labels"])
        again = B.rebuild_scan(source, rec, KITTI)
        assert np.array_equal(again.points, points) and np.array_equal(again.semantic, sem)
    # Beam-32 keeps 64 rows; about half the returns are gone.
    b_side = B.read_sidecar(tmp_path / "beam32" / "shard_0")
    assert b_side["range_image"]["height"] == 64
    assert all(0.4 < s["num_points_out"] / s["num_points_in"] < 0.6 for s in b_side["scans"])
    # The domains index the generator reads.
    out = tmp_path / "index.json"
    idx = domains_index(settings, [tmp_path / "fog" / "shard_0", tmp_path / "beam32" / "shard_0"], out)
    out.write_text(json.dumps(idx))
    read = read_domains_index(out)
    assert list(read) == ["Fog", "Beam32"] and read["Fog"]["id"] == 2 and len(read["Fog"]["files"]) == 2
    with pytest.raises(InputError, match="not one complete set"):
        domains_index(settings, [tmp_path / "fog" / "shard_0"] * 2, out)

