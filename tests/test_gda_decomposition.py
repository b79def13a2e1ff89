"""The GDA decomposition study: the real pool, LaserMix, pseudo-labels of real scans with
their accuracy, pool runs through the CLI (real training), the study's assembly and its DAG."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from omnilidar.cli import main
from omnilidar.data import subsets
from omnilidar.downstream.seg.dataset import SegScanDataset, records_from_entries
from omnilidar.downstream.seg.label_spaces import get_label_space
from omnilidar.downstream.seg.lasermix import inclination, laser_mix
from omnilidar.downstream.seg.dataset import read_confidence
from omnilidar.downstream.seg.pseudo_label import pool_records
from omnilidar.errors import InputError
from omnilidar.io import semantickitti
from omnilidar.report import decomposition as dc

from test_downstream_seg import _eval, _index
from test_downstream_training import _settings, _write_sequence

SPACE = get_label_space("semantickitti")


def test_pool_is_disjoint_from_the_subset_and_evenly_spread(tmp_path):
    index = _index(tmp_path, 200)
    subset = subsets.make_subset(index, "train", 0.01)  # scans 0 and 100
    pool = subsets.make_pool(index, "train", subset, 4, "subset.json")
    names = [e["points"] for e in pool["entries"]]
    assert len(names) == 4 and not set(names) & {e["points"] for e in subset["entries"]}
    assert names == ["s/000001.bin", "s/000050.bin", "s/000101.bin", "s/000150.bin"]  # rest[floor(k * 198 / 4)]
    assert pool["excludes"] == {"subset": "subset.json", "num_scans": 2}
    assert subsets.make_pool(index, "train", subset, 4, "subset.json") == pool  # no randomness
    with pytest.raises(InputError, match="198 scans outside"):
        subsets.make_pool(index, "train", subset, 199, "subset.json")


def _sequence_index(tmp_path, sizes):
    """An index whose train split is sequences "00", "01", ... of the given sizes."""
    entries = [{"points": f"{q:02d}/{i:06d}.bin", "labels": f"{q:02d}/{i:06d}.label", "num_points": 10,
                "sequence": f"{q:02d}", "frame": f"{i:06d}"} for q, n in enumerate(sizes) for i in range(n)]
    path = tmp_path / "index.json"
    path.write_text(json.dumps({"dataset": "semantickitti", "splits": {"train": entries, "val": entries[:2]}}))
    return path


def test_heldout_takes_whole_last_sequences_and_the_pool_leaves_them_out(tmp_path):
    index = _sequence_index(tmp_path, [50, 50, 50, 30, 20])
    subset = subsets.make_subset(index, "train", 0.01)  # scans 0 and 100: sequences 00 and 02
    held = subsets.make_heldout(index, "train", subset, 40, "subset.json")
    # The last sequences without a subset scan (04, then 03) until they hold 40 scans, spread evenly.
    assert held["excludes"]["sequences"] == ["03", "04"] and held["num_scans"] == 40
    assert {e["sequence"] for e in held["entries"]} == {"03", "04"}
    assert subsets.make_heldout(index, "train", subset, 20, "subset.json")["excludes"]["sequences"] == ["04"]
    pool = subsets.make_pool(index, "train", subset, 30, "subset.json", held, "heldout.json")
    assert {e["sequence"] for e in pool["entries"]} == {"00", "01", "02"}  # never a held-out sequence
    assert pool["excludes"]["heldout_sequences"] == ["03", "04"]
    assert not {e["points"] for e in pool["entries"]} & {e["points"] for e in subset["entries"]}
    with pytest.raises(InputError, match="148 scans outside the subset subset.json and the sequences"):
        subsets.make_pool(index, "train", subset, 149, "subset.json", held, "heldout.json")
    with pytest.raises(InputError, match="holds 100 scans in sequences without a scan of subset.json"):
        subsets.make_heldout(index, "train", subset, 101, "subset.json")
    (tmp_path / "plain").mkdir()
    with pytest.raises(InputError, match="names no sequence"):
        subsets.make_heldout(_index(tmp_path / "plain", 200), "train", subset, 5, "subset.json")


def test_make_subset_cli_writes_a_heldout_set_and_a_pool_outside_it(tmp_path):
    index = _sequence_index(tmp_path, [50, 50, 50, 30, 20])
    out = {name: str(tmp_path / f"{name}.json") for name in ("s", "h", "p", "bad")}
    assert main(["make-subset", "--index", str(index), "--percent", "1", "--out", out["s"]]) == 0
    assert main(["make-subset", "--index", str(index), "--exclude", out["s"], "--whole-sequences", "--count", "20",
                 "--out", out["h"]]) == 0
    assert main(["make-subset", "--index", str(index), "--exclude", out["s"], "--heldout", out["h"], "--count", "8",
                 "--out", out["p"]]) == 0
    assert not {e["sequence"] for e in subsets.read_subset(out["p"])["entries"]} & {"04"}
    assert main(["make-subset", "--index", str(index), "--percent", "1", "--whole-sequences", "--out", out["bad"]]) != 0
    assert not (tmp_path / "bad.json").exists()


def test_make_subset_cli_needs_percent_or_a_pool_request(tmp_path):
    index = _index(tmp_path, 50)
    assert main(["make-subset", "--index", str(index), "--percent", "10", "--out", str(tmp_path / "s.json")]) == 0
    assert main(["make-subset", "--index", str(index), "--exclude", str(tmp_path / "s.json"), "--count", "3",
                 "--out", str(tmp_path / "p.json")]) == 0
    assert subsets.read_subset(tmp_path / "p.json")["num_scans"] == 3
    assert main(["make-subset", "--index", str(index), "--exclude", str(tmp_path / "s.json"),
                 "--out", str(tmp_path / "q.json")]) != 0
    assert not (tmp_path / "q.json").exists()


def _cloud(pitch_deg: np.ndarray, label: int) -> tuple[np.ndarray, np.ndarray]:
    pitch = np.radians(pitch_deg)
    xyz = np.column_stack([10 * np.cos(pitch), np.zeros_like(pitch), 10 * np.sin(pitch)])
    points = np.column_stack([xyz, np.ones(len(pitch))]).astype(np.float32)
    return points, np.full(len(pitch), label, np.uint8)


def test_lasermix_takes_alternate_inclination_bands_from_each_scan():
    a = _cloud(np.linspace(-24, 2, 261), 1)
    b = _cloud(np.linspace(-24, 2, 261) + 0.05, 2)
    points, labels = laser_mix(a, b, np.random.default_rng(0))
    pitch = np.degrees(inclination(points))
    # Sorting the mix by inclination, the source (label) changes band by band: as many runs
    # as bands, each run from one scan, neighbouring runs from different scans.
    runs = np.flatnonzero(np.diff(labels[np.argsort(pitch)].astype(int))) + 1
    assert 2 <= len(runs) + 1 <= 6
    assert 0.3 < (labels == 1).mean() < 0.7
    # Points keep their own labels and are not altered.
    assert set(map(tuple, points[labels == 1])) <= set(map(tuple, a[0]))
    again = laser_mix(a, b, np.random.default_rng(0))
    assert np.array_equal(again[0], points) and np.array_equal(again[1], labels)


def test_lasermix_draws_are_part_of_the_seeded_training_stream(tmp_path):
    real = records_from_entries(_write_sequence(tmp_path / "a", 2, 0), "semantickitti")
    extra = records_from_entries(_write_sequence(tmp_path / "b", 2, 1), "semantickitti")
    data = SegScanDataset(real + extra, SPACE, None, seed=3, lasermix_from=2)
    mixed = data[(7, 2)]
    plain = SegScanDataset(real + extra, SPACE, None, seed=3)[(7, 2)]
    assert len(mixed["points"]) != len(plain["points"]) or not np.array_equal(mixed["points"], plain["points"])
    assert np.array_equal(data[(7, 2)]["points"], mixed["points"])  # same draw, same mix
    # Draws of the labelled scans are not mixed.
    assert np.array_equal(data[(7, 0)]["points"], SegScanDataset(real, SPACE, None, seed=3)[(7, 0)]["points"])


@pytest.fixture(scope="module")
def study_tree(tmp_path_factory):
    """A tiny SemanticKITTI-like index, a subset, a pool, and a labeler trained on it (CLI)."""
    root = tmp_path_factory.mktemp("decomposition")
    entries = _write_sequence(root / "train", 6, 0)
    index = root / "index.json"
    index.write_text(json.dumps({"dataset": "semantickitti", "splits": {"train": entries, "val": entries[:2]}}))
    settings = json.dumps(_settings(2))
    assert main(["make-subset", "--index", str(index), "--percent", "34", "--out", str(root / "subset.json")]) == 0
    assert main(["make-subset", "--index", str(index), "--exclude", str(root / "subset.json"), "--count", "3",
                 "--out", str(root / "pool.json")]) == 0
    assert main(["train-segmentor", "--backbone", "minkunet", "--subset", str(root / "subset.json"),
                 "--settings", settings, "--work-dir", str(root / "work_labeler"),
                 "--out", str(root / "labeler.pt")]) == 0
    return root, settings


def test_pseudo_labels_of_the_pool_record_their_accuracy_against_truth(study_tree):
    root, _ = study_tree
    out = root / "pool_labels"
    assert main(["pseudo-label", "--labeler", str(root / "labeler.pt"), "--pool", str(root / "pool.json"),
                 "--settings", json.dumps({"device": "cpu"}), "--out", str(out)]) == 0
    side = json.loads((out / "sidecar.json").read_text())
    acc = side["accuracy_against_truth"]
    # Recompute the accuracy from the files: pseudo-labels against the pool's true labels.
    pool = subsets.read_subset(root / "pool.json")
    correct = total = 0
    for k, entry in enumerate(pool["entries"]):
        truth = semantickitti.to_train_ids(semantickitti.read_label(entry["labels"])[0])
        pred = semantickitti.to_train_ids(semantickitti.read_label(out / "labels" / f"{k:06d}.label")[0])
        keep = truth != 0
        correct += int((truth[keep] == pred[keep]).sum())
        total += int(keep.sum())
    assert acc["accuracy"] == pytest.approx(correct / total)
    records = pool_records(root / "pool.json", out)
    assert [r["labels"] for r in records] == [str(out / "labels" / f"{k:06d}.label") for k in range(3)]
    # Confidences beside the labels: one per point, a probability of the chosen class (>= 1/20).
    conf = read_confidence(records[0]["labels"], len(semantickitti.read_points(records[0]["points"])))
    assert conf is not None and conf.min() >= 0.05 - 1 / 255 and conf.max() <= 1.0
    # min_confidence ignores exactly the pseudo-labelled points below it, and only in training draws.
    threshold = float(np.median(conf))
    masked = SegScanDataset(records, SPACE, None, seed=0, min_confidence=threshold)
    plain = SegScanDataset(records, SPACE, None, seed=0)
    a, b = masked[(0, 0)]["labels"], plain[(0, 0)]["labels"]
    assert np.array_equal(a == 0, (b == 0) | (conf < threshold)) and np.array_equal(a[a > 0], b[a > 0])
    assert np.array_equal(masked[0]["labels"], b)  # evaluation items are never masked
    assert pool_records(root / "pool.json", None)[0]["labels"] == pool["entries"][0]["labels"]


def test_pool_runs_train_on_truth_pseudo_labels_or_lasermix(study_tree):
    root, settings = study_tree
    labels = root / "pool_labels"
    if not labels.exists():
        assert main(["pseudo-label", "--labeler", str(root / "labeler.pt"), "--pool", str(root / "pool.json"),
                     "--settings", json.dumps({"device": "cpu"}), "--out", str(labels)]) == 0
    weights = {}
    for role, flags in (("real_truth", []), ("real_pseudo", ["--pool-labels", str(labels)]),
                        ("lasermix", ["--pool-labels", str(labels), "--lasermix"])):
        out = root / f"{role}.pt"
        assert main(["train-segmentor", "--backbone", "minkunet", "--subset", str(root / "subset.json"),
                     "--settings", settings, "--work-dir", str(root / f"work_{role}"), "--out", str(out),
                     "--pool", str(root / "pool.json"), *flags]) == 0
        payload = torch.load(out, weights_only=True)
        assert payload["train"]["info"]["role"] == role
        assert payload["train"]["num_real"] == 2 and payload["train"]["num_generated"] == 3
        assert payload["train"]["lasermix"] == (role == "lasermix")
        weights[role] = payload["state_dict"]
    first = next(iter(weights["real_truth"]))
    assert not torch.equal(weights["real_truth"][first], weights["lasermix"][first])
    # Bad requests: one clear error, no checkpoint.
    bad = root / "bad.pt"
    assert main(["train-segmentor", "--backbone", "minkunet", "--subset", str(root / "subset.json"),
                 "--settings", settings, "--work-dir", str(root / "work_bad"), "--out", str(bad),
                 "--pool", str(root / "pool.json"), "--lasermix"]) != 0
    assert not bad.exists()


def _seeded(backbone, role, miou, seed):
    doc = _eval(backbone, role, miou)
    doc["seed"], doc["_path"] = seed, f"{backbone}_{role}_{seed}.json"
    return doc


def test_study_gains_are_paired_by_seed_and_name_the_costliest_link():
    values = {"supervised_only": [0.10, 0.12, 0.11], "real_truth": [0.20, 0.21, 0.22],
              "real_pseudo": [0.17, 0.18, 0.16], "gda": [0.09, 0.12, 0.10], "lasermix": [0.15, 0.16, 0.14]}
    evals = [_seeded("minkunet", role, m, s) for role, ms in values.items() for s, m in enumerate(ms)]
    study = dc.decomposition(evals)["minkunet"]
    assert study["seeds"] == [0, 1, 2]
    assert study["rows"]["real_truth"]["gain_over_supervised"]["per_seed"] == pytest.approx([0.10, 0.09, 0.11])
    assert study["links"]["pseudo_labels"]["mean"] == pytest.approx(0.04)
    assert study["links"]["samples"]["mean"] == pytest.approx((0.08 + 0.06 + 0.06) / 3)
    assert study["costliest_link"] == "samples"
    # The regime is checked on held-out train scans, never on val: without them there is no verdict.
    assert study["ceiling_clears_two_std"] is None and study["regime_check"]["set"] is None
    # The same test on val is reported beside it (gain 0.10 against 2 x the ceiling's 0.01 std).
    assert study["ceiling_on_evalset"]["ceiling_gain"]["mean"] == pytest.approx(0.10)
    assert study["ceiling_on_evalset"]["two_std"] == pytest.approx(2 * float(np.std([0.10, 0.12, 0.11], ddof=1)))
    assert study["ceiling_on_evalset"]["ceiling_clears_two_std"] is True
    heldout = {"supervised_only": [0.30, 0.31, 0.32], "real_truth": [0.40, 0.30, 0.45]}
    for e in evals:
        role = e["train"]["info"]["role"]
        m = heldout.get(role, [0.2] * 3)[e["seed"]]
        e["sets"]["heldout"] = {**e["sets"]["val"], "miou": m}
    check = dc.decomposition(evals)["minkunet"]["regime_check"]
    assert check["set"] == "heldout" and check["ceiling_gain"]["per_seed"] == pytest.approx([0.10, -0.01, 0.13])
    assert check["two_std"] == pytest.approx(2 * float(np.std([0.40, 0.30, 0.45], ddof=1)))
    assert check["ceiling_clears_two_std"] is False  # 0.073 mean gain < 2 x 0.076
    for e in evals:
        if e["train"]["info"]["role"] == "real_truth":
            e["sets"]["heldout"]["miou"] = [0.40, 0.41, 0.42][e["seed"]]
    assert dc.decomposition(evals)["minkunet"]["ceiling_clears_two_std"] is True
    assert study["generated_share_of_ceiling"] == pytest.approx((-0.01 + 0 - 0.01) / 3 / 0.10)
    # A row missing, or a row run with other seeds, is an error naming it.
    with pytest.raises(InputError, match="lasermix"):
        dc.decomposition([e for e in evals if e["train"]["info"]["role"] != "lasermix"])
    with pytest.raises(InputError, match="seeds"):
        dc.decomposition([e for e in evals if not (e["train"]["info"]["role"] == "gda" and e["seed"] == 2)])


def test_one_seed_never_claims_the_ceiling_clears_the_noise():
    evals = [_seeded("spvcnn", role, m, 0) for role, m in
             (("supervised_only", 0.1), ("real_truth", 0.5), ("real_pseudo", 0.4), ("gda", 0.2), ("lasermix", 0.3))]
    for e in evals:
        e["sets"]["heldout"] = dict(e["sets"]["val"])
    study = dc.decomposition(evals)["spvcnn"]
    # A 40-point ceiling gain on the held-out scans, but one seed: no claim.
    assert study["regime_check"]["ceiling_gain"]["mean"] == pytest.approx(0.4)
    assert study["ceiling_clears_two_std"] is False and study["rows"]["generated"]["miou_std"] is None


def test_decomposition_command_writes_result_and_figure(tmp_path, capsys):
    paths = []
    for role, ms in {"supervised_only": [0.10, 0.12], "real_truth": [0.2, 0.22], "real_pseudo": [0.15, 0.16],
                     "gda": [0.11, 0.1], "lasermix": [0.14, 0.13]}.items():
        for seed, m in enumerate(ms):
            doc = _seeded("minkunet", role, m, seed)
            doc["train"]["info"]["dataset"] = "semantickitti"
            path = tmp_path / f"{role}_{seed}.json"
            path.write_text(json.dumps(doc))
            paths.append(str(path))
    labeler = tmp_path / "labeler.json"
    labeler.write_text(json.dumps(_seeded("minkunet", "supervised_only", 0.3, 0)))
    pool = tmp_path / "pool_labels"
    pool.mkdir()
    (pool / "sidecar.json").write_text(json.dumps({"accuracy_against_truth": {"miou": 0.42}}))
    out, fig = tmp_path / "gda_decomposition.json", tmp_path / "gda_decomposition.png"
    assert main(["gda-decomposition", "--evaluations", *paths, "--pool-labels", str(pool),
                 "--labeler-evaluation", str(labeler), "--settings", "{}", "--seed", "0",
                 "--data-source", json.dumps({"semantickitti": {"root": "data/synthetic/semantickitti", "kind": "synthetic"}}), "--out", str(out), "--figure", str(fig)]) == 0
    doc = json.loads(out.read_text())
    study = doc["backbones"]["minkunet"]
    assert study["rows"]["real_truth"]["miou_mean"] == pytest.approx(0.21)
    assert study["costliest_link"] == "pseudo_labels" or study["costliest_link"] == "samples"
    assert doc["pool_pseudo_labels_against_truth"] == {"miou": 0.42} and doc["labeler"]["val_miou"] == 0.3
    assert fig.stat().st_size > 10_000 and fig.read_bytes()[:4] == b"\x89PNG"
    assert "+N real, true labels" in capsys.readouterr().out
    # An attempt's own labeler is scored beside the fixed one.
    robust = tmp_path / "robust.json"
    robust.write_text(json.dumps(_seeded("minkunet", "supervised_only", 0.28, 0)))
    settings = json.dumps({"experiments": {"gda_decomposition": {"attempts": {"robust": {"labeler": {"batch_size": 1}}}}}})
    assert main(["gda-decomposition", "--evaluations", *paths, "--pool-labels", str(pool),
                 "--labeler-evaluation", str(labeler), "--attempt-labeler", f"robust={robust}", "--settings", settings,
                 "--seed", "0", "--data-source", json.dumps({"semantickitti": {"root": "data/synthetic/semantickitti",
                                                                              "kind": "synthetic"}}),
                 "--out", str(out), "--figure", str(fig)]) == 0
    assert json.loads(out.read_text())["attempt_labelers"]["robust"]["val_miou"] == 0.28
    assert main(["gda-decomposition", "--evaluations", *paths, "--pool-labels", str(pool),
                 "--labeler-evaluation", str(labeler), "--attempt-labeler", f"other={robust}", "--settings", settings,
                 "--seed", "0", "--data-source", json.dumps({"semantickitti": {"root": "x", "kind": "synthetic"}}),
                 "--out", str(tmp_path / "x.json"),
                 "--figure", str(fig)]) != 0
    assert not (tmp_path / "x.json").exists()
    # A missing row: one clear error, nothing written.
    out.unlink()
    assert main(["gda-decomposition", "--evaluations", *paths[:-2], "--pool-labels", str(pool),
                 "--labeler-evaluation", str(labeler), "--settings", "{}", "--seed", "0",
                 "--data-source", json.dumps({"semantickitti": {"root": "data/synthetic/semantickitti", "kind": "synthetic"}}), "--out", str(out), "--figure", str(fig)]) != 0
    assert not out.exists()


def test_attempts_are_scored_against_the_plain_generated_row():
    values = {"supervised_only": [0.10, 0.12], "real_truth": [0.2, 0.22], "real_pseudo": [0.15, 0.16],
              "gda": [0.11, 0.10], "lasermix": [0.14, 0.13]}
    evals = [_seeded("minkunet", role, m, s) for role, ms in values.items() for s, m in enumerate(ms)]
    tried = [_seeded("minkunet", "gda", m, s) for s, m in enumerate([0.13, 0.11])]
    study = dc.decomposition(evals, {"confident": tried})["minkunet"]
    assert study["attempts"]["confident"]["gain_over_generated"]["per_seed"] == pytest.approx([0.02, 0.01])
    assert study["attempts"]["confident"]["gain_over_supervised"]["mean"] == pytest.approx(0.01)
    # README's block shows the attempt as a row and its seed-paired gain over the plain generated row.
    from omnilidar.report.readme import gda_decomposition

    text = gda_decomposition({"backbones": {"minkunet": study}, "setup": {"evalset": "val"},
                              "attempts": {"confident": {"mixing": {"min_confidence": 0.6}}}})
    assert "| +N generated, attempt `confident` | 12.00 +- 1.41 |" in text
    assert "attempt `confident` against the plain generated row: 1.50 +- 0.71 points (seed by seed 2.00, 1.00)" in text
    with pytest.raises(InputError, match="seeds"):
        dc.decomposition(evals, {"confident": tried[:1]})


def test_simulated_pool_runs_the_pool_through_the_domain_scene_with_labels(study_tree, tmp_path):
    root, settings = study_tree
    out = tmp_path / "fog_pool"
    assert main(["simulate-pool", "fog", "--index", str(root / "index.json"), "--pool", str(root / "pool.json"),
                 "--settings", "{}", "--seed", "0", "--out", str(out)]) == 0
    pool = subsets.read_subset(out / "pool.json")
    real = subsets.read_subset(root / "pool.json")
    assert pool["num_scans"] == real["num_scans"] == 3 and pool["simulated"]["domain"] == "fog"
    side = json.loads((out / "sidecar.json").read_text())
    assert all(s["effects"][0]["name"] == "fog" for s in side["scans"])
    for entry, source in zip(pool["entries"], real["entries"]):
        points = semantickitti.read_points(entry["points"])
        labels = semantickitti.read_label(entry["labels"])[0]
        assert len(labels) == len(points) and entry["source"] == source["points"]
    records = pool_records(out / "pool.json", None)
    assert len(records) == 3
    # Same seed, same scans; the run is a simulated row.
    again = tmp_path / "again"
    assert main(["simulate-pool", "fog", "--index", str(root / "index.json"), "--pool", str(root / "pool.json"),
                 "--settings", "{}", "--seed", "0", "--out", str(again)]) == 0
    assert (again / "velodyne" / "000001.bin").read_bytes() == (out / "velodyne" / "000001.bin").read_bytes()
    run = tmp_path / "sim.pt"
    assert main(["train-segmentor", "--backbone", "minkunet", "--subset", str(root / "subset.json"),
                 "--settings", settings, "--work-dir", str(tmp_path / "work"), "--out", str(run),
                 "--pool", str(out / "pool.json"), "--pool-source", "simulated"]) == 0
    assert torch.load(run, weights_only=True)["train"]["info"]["role"] == "simulated"


def test_weather_study_scores_the_corruption_averaged_over_severities():
    def doc(role, seed, by_severity):
        d = _seeded("minkunet", role, 0.5, seed)
        names = list(d["sets"]["val"]["iou"])
        for sev, m in by_severity.items():
            d["sets"][f"fog/{sev}"] = {"miou": m, "iou": {n: m for n in names}, "miou_nanmean": m,
                                       "accuracy": 0.9, "num_scans": 2}
        return d
    base = {"supervised_only": 0.10, "real_truth": 0.20, "real_pseudo": 0.16, "gda": 0.12, "lasermix": 0.15,
            "simulated": 0.22}
    evals = [doc(role, s, {"light": m + 0.01 * s, "heavy": m - 0.02 + 0.01 * s})
             for role, m in base.items() for s in range(2)]
    study = dc.decomposition(evals, evalset="fog")["minkunet"]
    assert list(study["rows"]) == [*dc.ROWS, "simulated"] and study["evalset"] == "fog"
    assert study["rows"]["simulated"]["miou"] == pytest.approx([0.21, 0.22])
    assert study["links"]["vs_simulation"]["mean"] == pytest.approx(0.10)
    with pytest.raises(InputError, match="no snow/<severity> sets"):
        dc.decomposition(evals, evalset="snow")


def test_max_pool_takes_the_first_n_pool_scans(study_tree, tmp_path):
    root, settings = study_tree
    args = ["train-segmentor", "--backbone", "minkunet", "--subset", str(root / "subset.json"),
            "--settings", settings, "--work-dir", str(tmp_path / "work"), "--pool", str(root / "pool.json")]
    assert main([*args, "--out", str(tmp_path / "two.pt"), "--max-pool", "2"]) == 0
    train = torch.load(tmp_path / "two.pt", weights_only=True)["train"]
    assert train["num_generated"] == 2 and train["info"]["max_pool"] == 2
    assert main([*args, "--out", str(tmp_path / "four.pt"), "--max-pool", "4"]) != 0  # the pool holds 3
    assert not (tmp_path / "four.pt").exists()


def test_heldout_scans_avoid_subset_and_pool_and_are_scored_as_their_own_set(study_tree, tmp_path):
    root, _ = study_tree
    out = tmp_path / "heldout.json"
    assert main(["make-subset", "--index", str(root / "index.json"), "--exclude", str(root / "subset.json"),
                 str(root / "pool.json"), "--count", "1", "--out", str(out)]) == 0
    held = {e["points"] for e in subsets.read_subset(out)["entries"]}
    used = {e["points"] for name in ("subset.json", "pool.json") for e in subsets.read_subset(root / name)["entries"]}
    assert len(held) == 1 and not held & used
    scores = tmp_path / "scores.json"
    assert main(["evaluate-segmentor", "--checkpoint", str(root / "labeler.pt"), "--subset-set", f"heldout={out}",
                 "--settings", json.dumps({"device": "cpu"}), "--out", str(scores)]) == 0
    assert json.loads(scores.read_text())["sets"]["heldout"]["num_scans"] == 1


def test_simulated_pool_digest_follows_its_scans(study_tree, tmp_path):
    """pool.json (the file trainers key their resumable state by) carries each simulated file's
    digest, so a changed simulated scan changes it and a study run on it retrains instead of
    resuming a stale checkpoint."""
    from omnilidar.manifest import file_sha256

    root, _ = study_tree
    out = tmp_path / "fog_pool"
    assert main(["simulate-pool", "fog", "--index", str(root / "index.json"), "--pool", str(root / "pool.json"),
                 "--settings", "{}", "--seed", "0", "--out", str(out)]) == 0
    for entry in subsets.read_subset(out / "pool.json")["entries"]:
        assert entry["sha256"] == [file_sha256(entry["points"]), file_sha256(entry["labels"])]


def test_round_trip_pool_keeps_one_point_per_pixel_with_its_true_label(study_tree, tmp_path):
    """round-trip-pool: the pool through the domain's range image and back, labels carried; a
    narrower image keeps fewer points; its runs train as round_trip_truth / round_trip_pseudo."""
    root, settings = study_tree
    kept = {}
    for width in (512, 128):
        out = tmp_path / f"trip{width}"
        domains = json.dumps({"range_image": {"height": 64, "width": width}})
        assert main(["round-trip-pool", "vehicle", "--index", str(root / "index.json"), "--pool",
                     str(root / "pool.json"), "--settings", domains, "--out", str(out)]) == 0
        pool = subsets.read_subset(out / "pool.json")
        real = subsets.read_subset(root / "pool.json")
        assert pool["num_scans"] == 3 and pool["round_trip"]["range_image"]["width"] == width
        kept[width] = 0
        for entry, source in zip(pool["entries"], real["entries"]):
            points = semantickitti.read_points(entry["points"])
            labels = semantickitti.read_label(entry["labels"])[0]
            truth = set(semantickitti.read_label(source["labels"])[0].tolist())
            assert len(labels) == len(points) > 0 and set(labels.tolist()) <= truth
            kept[width] += len(points)
    assert kept[128] < kept[512]
    out = tmp_path / "trip512"
    labels = tmp_path / "trip_labels"
    assert main(["pseudo-label", "--labeler", str(root / "labeler.pt"), "--pool", str(out / "pool.json"),
                 "--settings", json.dumps({"device": "cpu"}), "--out", str(labels)]) == 0
    for role, flags in (("round_trip_truth", []), ("round_trip_pseudo", ["--pool-labels", str(labels)])):
        run = tmp_path / f"{role}.pt"
        assert main(["train-segmentor", "--backbone", "minkunet", "--subset", str(root / "subset.json"),
                     "--settings", settings, "--work-dir", str(tmp_path / f"work_{role}"), "--out", str(run),
                     "--pool", str(out / "pool.json"), "--pool-source", "round_trip", *flags]) == 0
        assert torch.load(run, weights_only=True)["train"]["info"]["role"] == role


def test_round_trip_rows_measure_each_link_from_the_ceiling_to_gda():
    values = {"supervised_only": [0.10, 0.12, 0.11], "real_truth": [0.20, 0.21, 0.22],
              "real_pseudo": [0.17, 0.18, 0.16], "gda": [0.09, 0.12, 0.10], "lasermix": [0.15, 0.16, 0.14],
              "round_trip_truth": [0.19, 0.21, 0.20], "round_trip_pseudo": [0.12, 0.13, 0.14]}
    evals = [_seeded("minkunet", role, m, s) for role, ms in values.items() for s, m in enumerate(ms)]
    study = dc.decomposition(evals)["minkunet"]
    assert list(study["rows"]) == [*dc.ROWS, "round_trip_truth", "round_trip_pseudo"]
    assert study["links"]["resolution"]["per_seed"] == pytest.approx([0.01, 0.0, 0.02])
    assert study["links"]["labels"]["per_seed"] == pytest.approx([0.07, 0.08, 0.06])
    assert study["links"]["generator"]["per_seed"] == pytest.approx([0.03, 0.01, 0.04])
    assert study["costliest_link"] == "labels"  # along the chain once the round-trip rows are there
    # The three links add up to the whole gap between the ceiling and GDA, seed by seed.
    total = np.sum([study["links"][k]["per_seed"] for k in dc.CHAIN], axis=0)
    gap = np.asarray(values["real_truth"]) - np.asarray(values["gda"])
    assert total == pytest.approx(gap)


def test_strength_attempts_make_a_curve_per_generator_and_place_where_scans_stop_paying(tmp_path):
    values = {"supervised_only": [0.10, 0.12], "real_truth": [0.20, 0.22], "real_pseudo": [0.17, 0.18],
              "gda": [0.04, 0.06], "lasermix": [0.15, 0.16], "round_trip_truth": [0.19, 0.21],
              "round_trip_pseudo": [0.16, 0.18]}
    evals = [_seeded("minkunet", role, m, s) for role, ms in values.items() for s, m in enumerate(ms)]
    runs = {"sources": [0.16, 0.18], "long_sources": [0.16, 0.18], "edit50": [0.13, 0.15], "edit75": [0.09, 0.11],
            "long_edit75": [0.12, 0.14], "long": [0.08, 0.10], "share25": [0.2, 0.2]}
    requested = {"sources": {"generator": {"sampling": {"strength": 0.001}}},
                 "long_sources": {"generator": {"training": {"iterations": 3000}, "sampling": {"strength": 0.001}}},
                 "edit50": {"generator": {"sampling": {"strength": 0.5}}},
                 "edit75": {"generator": {"sampling": {"strength": 0.75}}},
                 "long_edit75": {"generator": {"training": {"iterations": 3000}, "sampling": {"strength": 0.75}}},
                 "long": {"generator": {"training": {"iterations": 3000}}},
                 "share25": {"mixing": {"generated_share": 0.25}}}  # not a strength point
    tried = {n: [_seeded("minkunet", "gda", m, s) for s, m in enumerate(ms)] for n, ms in runs.items()}
    study = dc.decomposition(evals, tried)["minkunet"]
    curves = dc.strength_curves(study, requested, 300)
    assert list(curves) == ["300", "3000"]
    main_curve, long_curve = curves["300"], curves["3000"]
    assert main_curve["strength"] == [0.001, 0.5, 0.75, 1.0]
    assert main_curve["rows"] == ["sources", "edit50", "edit75", "generated"]
    assert main_curve["gain_mean"] == pytest.approx([0.06, 0.03, -0.01, -0.06])
    # between 0.5 and 0.75, linearly in log strength
    assert main_curve["crossing_strength"] == pytest.approx(10 ** (np.log10(0.5) + np.log10(1.5) * 0.03 / 0.04))
    assert long_curve["strength"] == [0.001, 0.75, 1.0] and long_curve["gain_mean"] == pytest.approx([0.06, 0.02, -0.02])
    assert long_curve["crossing_strength"] == pytest.approx(0.75 ** 0.5)
    trend = dc.strength_trend(curves)
    slope = (0.75 ** 0.5 - main_curve["crossing_strength"]) / 1.0  # one decade of iterations
    assert trend["slope_per_decade"] == pytest.approx(slope)
    assert trend["iterations_at_strength_1"] == pytest.approx(3000 * 10 ** ((1 - 0.75 ** 0.5) / slope))
    assert "two budgets" in trend["note"]
    assert dc.log_crossing([0.001, 1.0], [-0.01, -0.02]) is None  # never pays
    assert dc.log_crossing([0.001, 1.0], [0.01, 0.02]) is None  # always pays
    flat = dc.strength_trend({"a": {"iterations": 300, "crossing_strength": 0.6},
                              "b": {"iterations": 3000, "crossing_strength": 0.5}})
    assert flat["iterations_at_strength_1"] is None and "does not move" in flat["note"]
    creeping = dc.strength_trend({"a": {"iterations": 300, "crossing_strength": 0.007},
                                  "b": {"iterations": 3000, "crossing_strength": 0.008}})
    assert creeping["slope_per_decade"] == pytest.approx(0.001)
    assert creeping["iterations_at_strength_1"] is None and "beyond 1e12" in creeping["note"]
    # Without a strength attempt there is no curve.
    assert dc.strength_curves(study, {"share25": requested["share25"], "long": requested["long"]}, 300) == {}
    # Edits under their sources' true labels make a curve of their own, which the trend leaves out.
    carried = {"true50": {"labels": "carried", "generator": {"sampling": {"strength": 0.5}}},
               "true001": {"labels": "carried", "generator": {"sampling": {"strength": 0.001}}}}
    tried |= {"true50": [_seeded("minkunet", "gda", m, s) for s, m in enumerate([0.10, 0.12])],
              "true001": [_seeded("minkunet", "gda", m, s) for s, m in enumerate([0.15, 0.17])]}
    with_true = dc.strength_curves(dc.decomposition(evals, tried)["minkunet"], requested | carried, 300)
    assert list(with_true) == ["300", "300 carried", "3000"] and with_true["300"] == main_curve
    true_curve = with_true["300 carried"]
    assert true_curve["labels"] == "carried" and true_curve["rows"] == ["true001", "true50"]
    assert true_curve["gain_mean"] == pytest.approx([0.05, 0.0]) and true_curve["crossing_strength"] is None
    true_curve["crossing_strength"] = 0.9  # whatever it is, the labeler's curves alone make the trend
    assert dc.strength_trend(with_true) == trend
    # A generator of another recipe (here another prior) makes its own curve, named by what it changes.
    prior = {"prior02": {"generator": {"diffusion": {"prior": "domain_mean"}, "training": {"iterations": 3000},
                                       "sampling": {"strength": 0.02}}}}
    tried |= {"prior02": [_seeded("minkunet", "gda", m, s) for s, m in enumerate([0.11, 0.13])]}
    with_prior = dc.strength_curves(dc.decomposition(evals, tried)["minkunet"], requested | prior, 300)
    assert with_prior["3000 (diffusion.prior domain_mean)"]["rows"] == ["prior02"]
    assert with_prior["3000"] == long_curve and dc.curve_words(with_prior["3000 (diffusion.prior domain_mean)"]) == \
        " (diffusion.prior domain_mean)"
    with_prior["3000 (diffusion.prior domain_mean)"]["crossing_strength"] = 0.9
    assert dc.strength_trend(with_prior) == trend
    # So do the same edits under an attempt's own labeler, named by its keys, and out of the trend.
    robust = {"robust02": {"labeler": {"augmentation": {"range_jitter": 0.05}},
                           "generator": {"diffusion": {"prior": "domain_mean"}, "training": {"iterations": 3000},
                                         "sampling": {"strength": 0.02}}}}
    tried |= {"robust02": [_seeded("minkunet", "gda", m, s) for s, m in enumerate([0.12, 0.14])]}
    with_robust = dc.strength_curves(dc.decomposition(evals, tried)["minkunet"], requested | prior | robust, 300)
    key = "3000 (diffusion.prior domain_mean) labeler (augmentation.range_jitter 0.05)"
    assert with_robust[key]["rows"] == ["robust02"] and with_robust[key]["gain_mean"] == pytest.approx([0.02])
    assert dc.curve_words(with_robust[key]) == " (diffusion.prior domain_mean), labeler (augmentation.range_jitter 0.05)"
    with_robust[key]["crossing_strength"] = 0.9
    assert dc.strength_trend(with_robust) == trend
    # README's block and the figure show them.
    from omnilidar.report.readme import gda_decomposition

    study["strength_curves"], study["strength_trend"] = curves, trend
    doc = {"backbones": {"minkunet": study}, "setup": {"evalset": "val", "percent": 1, "scans": 2, "domain": "vehicle"},
           "attempts": requested}
    text = gda_decomposition(doc)
    assert "generator of 300 iterations, gain over supervised only by sampling strength: 0.001: 6.00 +- 0.00, 0.5: 3.00 +- 0.00" in text
    assert "stops paying at strength 0.68" in text and "per decade of generator iterations" in text
    from omnilidar.report.readme import strength_short

    short = strength_short(doc)  # README's view: the curves alone
    assert "stops paying at strength 0.68" in short and "+N real" not in short
    dc.decomposition_figure(tmp_path / "fig.png", doc)
    assert (tmp_path / "fig.png").read_bytes()[:4] == b"\x89PNG"


def test_range_noise_attempts_make_a_precision_curve_and_place_where_scans_stop_paying(tmp_path):
    values = {"supervised_only": [0.10, 0.12], "real_truth": [0.20, 0.22], "real_pseudo": [0.17, 0.18],
              "gda": [0.04, 0.06], "lasermix": [0.15, 0.16], "round_trip_truth": [0.19, 0.21],
              "round_trip_pseudo": [0.16, 0.18]}
    evals = [_seeded("minkunet", role, m, s) for role, ms in values.items() for s, m in enumerate(ms)]
    real = {"labels": "carried", "generator": {"sampling": {"strength": 0.001, "keep_source": ["intensity"]}}}

    def noisy(std):
        return {**real, "generator": {"sampling": {**real["generator"]["sampling"], "range_noise": std}}}

    requested = {"true001": {"labels": "carried", "generator": {"sampling": {"strength": 0.001}}},
                 "noise01": noisy(0.01), "noise001": noisy(0.001), "noise1": noisy(0.1),
                 "labeler_noise": {"generator": {"sampling": {"strength": 0.001, "range_noise": 0.05}}},  # labeler's labels
                 "edit_noise": {**noisy(0.05), "generator": {"sampling": {"strength": 0.5, "range_noise": 0.05}}}}
    runs = {"true001": [0.15, 0.17], "noise001": [0.14, 0.16], "noise01": [0.12, 0.14], "noise1": [0.06, 0.08],
            "labeler_noise": [0.0, 0.0], "edit_noise": [0.0, 0.0]}
    tried = {n: [_seeded("minkunet", "gda", m, s) for s, m in enumerate(ms)] for n, ms in runs.items()}
    study = dc.decomposition(evals, tried)["minkunet"]
    curve = dc.range_noise_curve(study, requested)
    assert curve["noise_std"] == [0.001, 0.01, 0.1] and curve["rows"] == ["noise001", "noise01", "noise1"]
    assert curve["gain_mean"] == pytest.approx([0.04, 0.02, -0.04]) and curve["zero"]["row"] == "true001"
    # between 0.01 and 0.1, linearly in log noise
    assert curve["crossing_noise"] == pytest.approx(10 ** (-2 + 0.02 / 0.06))
    assert dc.range_noise_curve(study, {"true001": requested["true001"]}) is None
    # Noise attempts are not strength points: the strength curves leave them out.
    assert "noise01" not in str(dc.strength_curves(study, requested, 300))
    from omnilidar.report.readme import strength_short

    study["range_noise_curve"] = curve
    doc = {"backbones": {"minkunet": study}, "setup": {"evalset": "val", "percent": 1, "scans": 2, "domain": "vehicle"},
           "attempts": requested}
    short = strength_short(doc)
    assert "without noise (true001) 5.00 +- 0.00; 0.001: 4.00 +- 0.00" in short and "stops paying at 0.022" in short
    dc.decomposition_figure(tmp_path / "fig.png", doc)
    assert (tmp_path / "fig.png").read_bytes()[:4] == b"\x89PNG"


def test_sample_quality_scores_generated_scans_against_held_out_real_scans(study_tree, tmp_path):
    """sample-quality: the pool's own range images score JSD = MMD = 0 against the pool; noisy
    images score worse; too few scans is one clear error and no file."""
    from omnilidar.data.range_image import RangeImageSpec, encode, project
    from omnilidar.lidar.sensors import PRESETS

    root, _ = study_tree
    geometry = {"height": 32, "width": 256}
    spec = RangeImageSpec.from_sensor(PRESETS["kitti_hdl64e"], **geometry)
    pool = subsets.read_subset(root / "pool.json")
    rng = np.random.default_rng(0)
    for name, noise in (("same", 0.0), ("noisy", 0.3)):
        shard = tmp_path / name / "shard_0" / "range"
        shard.mkdir(parents=True)
        for k, entry in enumerate(pool["entries"]):
            proj = project(semantickitti.read_points(entry["points"]), spec)
            image = encode(proj.range_img, proj.intensity_img, spec)
            image[0] = np.clip(image[0] + noise * rng.standard_normal(image[0].shape), -1, 1)
            np.savez(shard / f"{k:06d}.npz", image=image.astype(np.float32))
    scores = {}
    for name in ("same", "noisy"):
        out = tmp_path / f"{name}.json"
        assert main(["sample-quality", "--subset", str(root / "pool.json"), "--samples",
                     str(tmp_path / name / "shard_0"), "--scans", "3", "--metrics", "JSD", "MMD",
                     "--range-image", json.dumps(geometry), "--out", str(out)]) == 0
        scores[name] = json.loads(out.read_text())
    assert scores["same"]["metrics"] == {"JSD": 0.0, "MMD": 0.0} and scores["same"]["n_real"] == 3
    assert scores["noisy"]["metrics"]["JSD"] > 0.01 and scores["noisy"]["metrics"]["MMD"] > 0
    bad = tmp_path / "bad.json"
    assert main(["sample-quality", "--subset", str(root / "pool.json"), "--samples", str(tmp_path / "same" / "shard_0"),
                 "--scans", "4", "--metrics", "JSD", "--range-image", json.dumps(geometry), "--out", str(bad)]) != 0
    assert not bad.exists()


def test_labeler_line_names_each_attempts_own_labeler():
    from omnilidar.report.readme import _labeler_line

    own = {"a": {"val_miou": 0.18, "val_iou": {"car": 0.4}}, "b": {"val_miou": 0.18, "val_iou": {"car": 0.4}},
           "c": {"val_miou": 0.1, "val_iou": {"car": 0.3}}}
    line = _labeler_line({"labeler": {"val_miou": 0.2, "val_iou": {"car": 0.5}},
                          "labeler_check": {"compared": True, "warning": None}, "attempt_labelers": own})
    assert line.startswith("Labeler (trained once on 100 % of the real train labels): val mIoU 20.00, car IoU 50.0")
    assert "Own labeler of `a`, `b`: val mIoU 18.00, car IoU 40.0." in line and "Own labeler of `c`: val mIoU 10.00" in line
