"""Segmentation GDA building blocks: subsets, label maps, data stream, pseudo-label
pairing, checkpoints, robustness scores and experiment assembly (no training)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from omnilidar.data import subsets
from omnilidar.downstream.seg import checkpoints, dataset, label_spaces, robustness
from omnilidar.downstream.seg.experiments import compare, robustness_result
from omnilidar.downstream.seg.pseudo_label import generated_records
from omnilidar.errors import InputError
from omnilidar.io import semantickitti


def _index(tmp_path, n):
    entries = [{"points": f"s/{i:06d}.bin", "labels": f"l/{i:06d}.label", "num_points": 10} for i in range(n)]
    path = tmp_path / "index.json"
    path.write_text(json.dumps({"dataset": "semantickitti", "splits": {"train": entries, "val": entries[:2]}}))
    return path


def test_subset_is_one_scan_out_of_every_k(tmp_path):
    index = _index(tmp_path, 250)
    one = subsets.make_subset(index, "train", 0.01)
    assert one["every"] == 100 and [e["points"] for e in one["entries"]] == ["s/000000.bin", "s/000100.bin", "s/000200.bin"]
    ten = subsets.make_subset(index, "train", 0.10)
    assert ten["num_scans"] == 25 and ten["entries"][1]["points"] == "s/000010.bin"
    assert subsets.make_subset(index, "train", 0.20)["every"] == 5
    assert subsets.make_subset(index, "train", 1.0)["num_scans"] == 250
    # Deterministic: the same index gives the same list, byte for byte.
    subsets.write_subset(one, tmp_path / "a.json")
    subsets.write_subset(subsets.make_subset(index, "train", 0.01), tmp_path / "b.json")
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()
    assert subsets.read_subset(tmp_path / "a.json")["num_scans"] == 3


def test_subset_bad_input(tmp_path):
    index = _index(tmp_path, 5)
    with pytest.raises(InputError, match="no split"):
        subsets.make_subset(index, "trian", 0.1)
    with pytest.raises(InputError, match="fraction"):
        subsets.every_k(0.0)
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(InputError, match="not a subset list"):
        subsets.read_subset(tmp_path / "bad.json")


def test_nuscenes_learning_map_and_mapping_from_semantickitti():
    nus = label_spaces.get_label_space("nuscenes")
    assert nus.num_classes == 16 and nus.num_ids == 17
    general = np.array([0, 2, 3, 9, 12, 14, 15, 16, 17, 18, 21, 22, 23, 24, 25, 26, 27, 28, 29, 30, 31])
    ids = label_spaces.nuscenes_train_ids(general)
    names = ["ignore", *nus.class_names]
    assert [names[i] for i in ids] == [
        "ignore", "pedestrian", "pedestrian", "barrier", "traffic_cone", "bicycle", "bus", "bus", "car",
        "construction_vehicle", "motorcycle", "trailer", "truck", "driveable_surface", "other_flat", "sidewalk",
        "terrain", "manmade", "ignore", "vegetation", "ignore"]
    sk = semantickitti.to_train_ids(np.array([0, 10, 31, 40, 44, 49, 50, 71, 80, 81, 20], np.uint16))
    mapped = label_spaces.semantickitti_to_nuscenes(sk)
    assert [names[i] for i in mapped] == [
        "ignore", "car", "bicycle", "driveable_surface", "driveable_surface", "other_flat", "manmade",
        "vegetation", "manmade", "manmade", "bus"]


def test_augmentation_is_seeded_rotation_and_scale():
    pts = np.random.default_rng(0).normal(size=(500, 4)).astype(np.float32)
    a = dataset.augment(pts, dataset.draw_rng(3, 7), True, (0.95, 1.05))
    b = dataset.augment(pts, dataset.draw_rng(3, 7), True, (0.95, 1.05))
    c = dataset.augment(pts, dataset.draw_rng(3, 8), True, (0.95, 1.05))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    ratio = np.linalg.norm(a[:, :3], axis=1) / np.linalg.norm(pts[:, :3], axis=1)
    assert np.allclose(ratio, ratio[0], atol=1e-5) and 0.95 <= ratio[0] <= 1.05  # isotropic scale
    assert np.array_equal(a[:, 3], pts[:, 3])  # intensity untouched
    plain = dataset.augment(pts, dataset.draw_rng(0, 0), False, (1.0, 1.0))
    assert np.array_equal(plain, pts)


def test_range_jitter_moves_points_along_their_rays_by_the_asked_size():
    rng = np.random.default_rng(1)
    direction = rng.normal(size=(20000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    dist = rng.uniform(2.0, 60.0, 20000)
    pts = np.concatenate([direction * dist[:, None], rng.uniform(size=(20000, 1))], axis=1).astype(np.float32)
    moved = dataset.jitter_ranges(pts, 0.03, np.random.default_rng(5))
    new_dist = np.linalg.norm(moved[:, :3].astype(np.float64), axis=1)
    cosine = np.sum(moved[:, :3] * pts[:, :3], axis=1) / (new_dist * dist)
    assert np.all(cosine > 1 - 1e-5)  # along the ray, outwards or inwards
    change = np.log(new_dist + 1.0) - np.log(dist + 1.0)
    assert abs(change.std() - 0.03) < 0.001 and abs(change.mean()) < 0.001
    assert np.array_equal(moved[:, 3], pts[:, 3])
    assert np.array_equal(moved, dataset.jitter_ranges(pts, 0.03, np.random.default_rng(5)))  # seeded
    # Through augment: 0 changes nothing (the draws of rotation and scale come first); > 0 jitters.
    plain = dataset.augment(pts, dataset.draw_rng(3, 7), True, (0.95, 1.05))
    assert np.array_equal(plain, dataset.augment(pts, dataset.draw_rng(3, 7), True, (0.95, 1.05), 0.0))
    jittered = dataset.augment(pts, dataset.draw_rng(3, 7), True, (0.95, 1.05), 0.05)
    assert not np.array_equal(plain, jittered)
    assert np.allclose(np.arctan2(jittered[:, 1], jittered[:, 0]), np.arctan2(plain[:, 1], plain[:, 0]), atol=1e-4)


def test_mixing_plans():
    concat = {"mode": "concat", "generated_share": 0.5}
    plan = dataset.epoch_plan(3, 5, concat, 0, 0)
    assert sorted(plan) == list(range(8))
    ratio = {"mode": "ratio", "generated_share": 0.75}
    plan = dataset.epoch_plan(4, 100, ratio, 0, 0)
    assert len(plan) == 16 and (plan < 4).sum() == 4  # 12 generated = 75 %
    nxt = dataset.epoch_plan(4, 100, ratio, 1, 0)
    assert set(plan[plan >= 4]).isdisjoint(nxt[nxt >= 4])  # generated scans cycle across epochs
    assert sorted(dataset.epoch_plan(3, 0, ratio, 0, 0)) == [0, 1, 2]


def test_batch_stream_is_deterministic_and_resumable():
    mix = {"mode": "concat", "generated_share": 0.5}
    s = dataset.MixedBatchSampler(3, 2, mix, 2, seed=5)
    it = iter(s)
    first = [next(it) for _ in range(6)]
    draws = [d for batch in first for d, _ in batch]
    assert draws == list(range(12))
    resumed = iter(dataset.MixedBatchSampler(3, 2, mix, 2, seed=5, skip=4))
    again = [next(resumed) for _ in range(6)]
    assert again[:4] == [[]] * 4 and again[4:] == first[4:]


def _write_shard(root, counts, labels_counts=None):
    samples, pseudo = root / "samples", root / "pseudo"
    (samples / "velodyne").mkdir(parents=True)
    (pseudo / "labels").mkdir(parents=True)
    for i, n in enumerate(counts):
        np.zeros((n, 4), np.float32).tofile(samples / "velodyne" / f"{i:06d}.bin")
    for i, n in enumerate(labels_counts or counts):
        np.zeros(n, np.uint32).tofile(pseudo / "labels" / f"{i:06d}.label")
    return samples, pseudo


def test_pseudo_label_shards_must_match_their_sample_shards(tmp_path):
    samples, pseudo = _write_shard(tmp_path / "ok", [5, 0, 7])
    records, empty = generated_records([samples], [pseudo])
    assert len(records) == 2 and empty == 1 and records[0]["format"] == "semantickitti"
    samples, pseudo = _write_shard(tmp_path / "count", [5, 7], [5, 6])
    with pytest.raises(InputError, match="does not match its sample shard"):
        generated_records([samples], [pseudo])
    samples, pseudo = _write_shard(tmp_path / "missing", [5, 7], [5])
    with pytest.raises(InputError, match="2 scans, 1 labels"):
        generated_records([samples], [pseudo])
    with pytest.raises(InputError, match="sample shards but"):
        generated_records([samples], [])


def test_missing_label_and_count_mismatch_are_input_errors(tmp_path):
    pts = tmp_path / "a.bin"
    np.zeros((4, 4), np.float32).tofile(pts)
    space = label_spaces.get_label_space("semantickitti")
    with pytest.raises(InputError, match="label file not found"):
        dataset.read_record({"points": str(pts), "labels": str(tmp_path / "a.label"), "format": "semantickitti"}, space)
    np.zeros(3, np.uint32).tofile(tmp_path / "a.label")
    with pytest.raises(InputError, match="has 3 labels but its scan has 4 points"):
        dataset.read_record({"points": str(pts), "labels": str(tmp_path / "a.label"), "format": "semantickitti"}, space)


def test_checkpoints_load_weights_only_and_reject_corrupt_files(tmp_path):
    state = {"w": torch.ones(2, 3), "b": torch.zeros(2)}
    checkpoints.save_payload({"state_dict": state, "model": {"backbone": "minkunet"}, "label_space": "semantickitti",
                              "voxel_size": 0.3}, tmp_path / "p.pt")
    raw = torch.load(tmp_path / "p.pt", weights_only=True)
    assert raw["format"] == checkpoints.FORMAT
    assert checkpoints.load_payload(tmp_path / "p.pt")["voxel_size"] == 0.3
    torch.save(state, tmp_path / "plain.pt")
    assert set(checkpoints.load_state_dict(tmp_path / "plain.pt")) == {"w", "b"}
    (tmp_path / "corrupt.pt").write_bytes(b"not a checkpoint at all")
    with pytest.raises(InputError, match="weights_only=True"):
        checkpoints.load_state_dict(tmp_path / "corrupt.pt")
    with pytest.raises(InputError, match="not found"):
        checkpoints.load_payload(tmp_path / "nope.pt")
    with pytest.raises(InputError, match="not an omnilidar segmentor checkpoint"):
        checkpoints.load_payload(tmp_path / "plain.pt")

    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    torch.save({"w": Evil()}, tmp_path / "evil.pt")
    with pytest.raises(InputError, match="weights_only=True"):
        checkpoints.load_state_dict(tmp_path / "evil.pt")
    torch.save({"w": torch.tensor([float("nan")])}, tmp_path / "nan.pt")
    with pytest.raises(InputError, match="NaN"):
        checkpoints.load_state_dict(tmp_path / "nan.pt")


def test_mce_and_mrr_hand_computed():
    sets = {"fog": {"light": 0.5, "heavy": 0.3}, "snow": {"light": 0.4, "heavy": 0.4}}
    base = {"fog": {"light": 0.6, "heavy": 0.4}, "snow": {"light": 0.4, "heavy": 0.4}}
    r = robustness.robustness(sets, clean=0.5, baseline_sets=base)
    assert r["ce"]["fog"] == pytest.approx(100 * (0.5 + 0.7) / (0.4 + 0.6))
    assert r["ce"]["snow"] == pytest.approx(100.0)
    assert r["mce"] == pytest.approx((120.0 + 100.0) / 2)
    assert r["rr"]["fog"] == pytest.approx(100 * 0.4 / 0.5) and r["rr"]["snow"] == pytest.approx(80.0)
    # The baseline itself scores exactly 100.
    assert robustness.robustness(base, 0.5, baseline_sets=base)["mce"] == pytest.approx(100.0)
    table = robustness.robustness({"fog": {"light": 0.5, "heavy": 0.5}}, 0.6,
                                  baseline_table=robustness.ROBO3D_MINKUNET18)
    assert table["ce"]["fog"] == pytest.approx(100 * 1.0 / (2 * (1 - 0.5587)))


def _eval(backbone, role, miou, sets=None, pct=1.0):
    names = list(semantickitti.CLASS_NAMES)
    scores = lambda m: {"miou": m, "miou_nanmean": m, "accuracy": 0.9, "num_scans": 2,  # noqa: E731
                        "iou": {n: m for n in names}}
    return {"_path": f"{backbone}_{role}.json", "checkpoint": "c.pt", "seed": 0, "class_names": names,
            "model": {"backbone": backbone}, "label_space": "semantickitti",
            "train": {"num_real": 2, "num_generated": 16 if role == "gda" else 0, "iterations": 40,
                      "mixing": {"mode": "concat"}, "seconds": 10.0,
                      "info": {"role": role, "percent": pct, "domains": ["vehicle"] if role == "gda" else []}},
            "sets": {"val": scores(miou), **{k: scores(v) for k, v in (sets or {}).items()}}, "seconds": 1.0}


def test_experiment_comparison_and_robustness():
    runs = compare("semkitti", [_eval("minkunet", "supervised_only", 0.2), _eval("minkunet", "gda", 0.3)])
    m = runs["minkunet"]
    assert m["miou_gain"] == pytest.approx(0.1) and m["gda_helped"]
    assert m["paper_miou"] == {"supervised_only": 40.39, "gda": 59.49}
    with pytest.raises(InputError, match="no gda"):
        compare("semkitti", [_eval("spvcnn", "supervised_only", 0.2)])
    corr = {"fog/light": 0.5, "fog/heavy": 0.3}
    res = robustness_result([_eval("minkunet", "supervised_only", 0.6, corr, 100),
                             _eval("minkunet", "gda", 0.6, {"fog/light": 0.6, "fog/heavy": 0.4}, 100)])
    assert res["minkunet"]["supervised_only"]["normalised_by_supervised_only"]["mce"] == pytest.approx(100.0)
    assert res["minkunet"]["gda"]["normalised_by_supervised_only"]["mce"] == pytest.approx(100 * 1.0 / 1.2)
    assert res["minkunet"]["gda"]["normalised_by_robo3d_minkunet18"]["ce"]["fog"] == pytest.approx(
        100 * 1.0 / (2 * (1 - 0.5587)))


def test_gda_result_records_the_labelers_own_quality(tmp_path, capsys):
    """A GDA result names the labeler's val mIoU and per-class IoU beside the runs."""
    import argparse
    import json

    from omnilidar.commands import gda_result

    paths = []
    for doc in (_eval("minkunet", "supervised_only", 0.2), _eval("minkunet", "gda", 0.3),
                {**_eval("minkunet", "labeler", 0.45), "checkpoint": "data/labeler/semantickitti.pt"}):
        path = tmp_path / f"{doc['train']['info']['role']}.json"
        path.write_text(json.dumps(doc))
        paths.append(str(path))
    parser = argparse.ArgumentParser()
    gda_result.add_arguments(parser)
    args = parser.parse_args(["--experiment", "semkitti_1pct", "--kind", "semkitti", "--settings", "{}",
                              "--seed", "0", "--data-source", '{"semantickitti": {"root": "data/synthetic/semantickitti", "kind": "synthetic"}}',
                              "--evaluations", *paths[:2],
                              "--labeler-evaluation", paths[2], "--out", str(tmp_path / "r.json"),
                              "--figure", str(tmp_path / "r.png")])
    assert gda_result.run(args) == 0
    labeler = json.loads((tmp_path / "r.json").read_text())["labeler"]
    assert labeler["val_miou"] == pytest.approx(0.45) and labeler["val_iou"]["car"] == pytest.approx(0.45)
    assert labeler["label_space"] == "semantickitti" and labeler["evaluation"] == paths[2]
    out = capsys.readouterr()
    assert "labeler (writes every pseudo-label): val mIoU 45.00" in out.out and "WARNING" not in out.err
    check = json.loads((tmp_path / "r.json").read_text())["labeler_check"]
    assert check["compared"] and check["warning"] is None
    assert check["students"]["minkunet"] == {"student_val_miou": 0.2, "student_seeds": 1, "labeler_val_miou": 0.45,
                                             "labeler_stronger": True}
    # A labeler weaker than the student it feeds: said in the JSON and on the terminal.
    weak = json.loads(open(paths[2]).read())
    weak["sets"]["val"]["miou"] = 0.15
    (tmp_path / "weak.json").write_text(json.dumps(weak))
    args.labeler_evaluation = str(tmp_path / "weak.json")
    assert gda_result.run(args) == 0
    check = json.loads((tmp_path / "r.json").read_text())["labeler_check"]
    assert check["students"]["minkunet"]["labeler_stronger"] is False
    assert "scores below the supervised-only minkunet (20.00)" in check["warning"]
    assert "WARNING: the labeler (val mIoU 15.00) scores below" in capsys.readouterr().err
    # An evaluation without the val set is one clear error naming the file.
    bad = json.loads(open(paths[2]).read())
    bad["sets"] = {"fog/light": bad["sets"]["val"]}
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    args.labeler_evaluation = str(tmp_path / "bad.json")
    with pytest.raises(InputError, match="no 'val' set"):
        gda_result.run(args)


def test_comparison_over_several_seeds_gives_mean_and_spread():
    def seeded(backbone, role, miou, seed):
        return {**_eval(backbone, role, miou), "seed": seed, "_path": f"{backbone}_{role}_{seed}.json"}

    evals = [seeded("minkunet", "supervised_only", m, s) for s, m in ((2, 0.24), (0, 0.20), (1, 0.22))]
    evals += [seeded("minkunet", "gda", m, s) for s, m in ((0, 0.25), (1, 0.21), (2, 0.29))]
    run = compare("semkitti", evals)["minkunet"]
    sup, gda = run["supervised_only"]["across_seeds"], run["gda"]["across_seeds"]
    assert sup["seeds"] == [0, 1, 2] and sup["miou"] == [0.20, 0.22, 0.24]
    assert sup["miou_mean"] == pytest.approx(0.22) and sup["miou_std"] == pytest.approx(0.02)
    assert gda["miou_mean"] == pytest.approx(0.25) and gda["miou_std"] == pytest.approx(0.04)
    assert run["miou_gain_per_seed"] == pytest.approx([0.05, -0.01, 0.05]) and run["seeds"] == 3
    assert run["miou_gain"] == pytest.approx(0.03) and run["gda_helped"]
    # The record's own scores are the configured (lowest) seed's run.
    assert run["supervised_only"]["scores"]["val"]["miou"] == pytest.approx(0.20)
    assert sup["iou_mean"]["car"] == pytest.approx(0.22)
    # One seed: no spread; unequal seed sets and a repeated seed are errors.
    single = compare("semkitti", [seeded("minkunet", "supervised_only", 0.2, 0), seeded("minkunet", "gda", 0.3, 0)])
    assert single["minkunet"]["gda"]["across_seeds"]["miou_std"] is None
    with pytest.raises(InputError, match="differ from GDA seeds"):
        compare("semkitti", evals[:3] + evals[3:5])
    with pytest.raises(InputError, match="with seed 0"):
        compare("semkitti", evals + [seeded("minkunet", "gda", 0.3, 0)])
