"""The GDA curve: --max-generated runs, the results/gda_curve.json target and its
workflow DAG, the sampler study reading the curve, readable log axes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from omnilidar.cli import main
from omnilidar.config import section_defaults
from omnilidar.downstream.seg.pseudo_label import generated_records
from omnilidar.errors import InputError
from omnilidar.io import semantickitti
from omnilidar.report.gda_curve import read_curve
from omnilidar.report.log_axis import nice_log_ticks, readable_log_x, tick_labels
from test_downstream_training import _scene  # road / sidewalk ground and a car box, raw labels
from test_generation_targets import _settings as tradeoff_settings
from test_generation_targets import fixture_dir  # noqa: F401  (the tiny generator and extractors)
from workflow_helpers import copy_workflow, planned_jobs, rerun_reasons, snakemake

TINY = "config/test.yaml"

# Every result names the datasets it used (omnilidar.data_source).
DATA_SOURCE = {"semantickitti": {"root": "/data/kitti", "kind": "real"},
               "pi3det": {"root": "data/synthetic/pi3det", "kind": "synthetic"}}
DATA_SOURCE_ARGS = ["--data-source", json.dumps(DATA_SOURCE)]


def _shards(root, sizes: list[list[int]], seed: int = 0):
    """Sample shards (velodyne/) and their pseudo-label shards (labels/), scans numbered
    across shards like `omnilidar sample` does; a size of 0 is an empty scan."""
    rng = np.random.default_rng(seed)
    samples, pseudo, g = [], [], 0
    for k, shard in enumerate(sizes):
        s, p = root / "samples" / f"shard_{k}", root / "pseudo" / f"shard_{k}"
        (s / "velodyne").mkdir(parents=True)
        (p / "labels").mkdir(parents=True)
        for n in shard:
            pts, lab = _scene(rng, n) if n else (np.zeros((0, 4), np.float32), np.zeros(0, np.uint32))
            semantickitti.write_points(s / "velodyne" / f"{g:06d}.bin", pts)
            lab.astype(np.uint32).tofile(p / "labels" / f"{g:06d}.label")
            g += 1
        samples.append(s)
        pseudo.append(p)
    return samples, pseudo


def test_generated_records_take_the_first_n_scans_in_shard_order(tmp_path):
    samples, pseudo = _shards(tmp_path, [[50, 0, 50], [50, 50, 50]])
    records, empty = generated_records(samples, pseudo, limit=4)
    # Shards in the given order, scans in name order; the empty scan counts but is left out.
    picked = [f"{Path(r['points']).parents[1].name}/{Path(r['points']).name}" for r in records]
    assert picked == ["shard_0/000000.bin", "shard_0/000002.bin", "shard_1/000003.bin"]
    assert empty == 1
    assert len(generated_records(samples, pseudo, limit=6)[0]) == 5
    with pytest.raises(InputError, match="hold 6 scans, fewer than the 7 asked for"):
        generated_records(samples, pseudo, limit=7)
    with pytest.raises(InputError, match=">= 1"):
        generated_records(samples, pseudo, limit=0)
    # A shard after the limit is never read (a broken one does not matter).
    bad_s, bad_p = _shards(tmp_path / "bad", [[50, 50]])
    (bad_p[0] / "labels" / "000001.label").unlink()
    assert len(generated_records([*samples, *bad_s], [*pseudo, *bad_p], limit=3)[0]) == 2
    with pytest.raises(InputError, match="does not match sample shard"):
        generated_records([*samples, *bad_s], [*pseudo, *bad_p])


def _subset(root) -> str:
    """A one-scan real label subset (make-subset's format) of a tiny sequence."""
    velo, lab = root / "real" / "velodyne", root / "real" / "labels"
    velo.mkdir(parents=True)
    lab.mkdir(parents=True)
    pts, sem = _scene(np.random.default_rng(9), 400)
    semantickitti.write_points(velo / "000000.bin", pts)
    semantickitti.write_label(lab / "000000.label", sem.astype(np.uint16))
    doc = {"format": "omnilidar-subset/1", "dataset": "semantickitti", "split": "train", "fraction": 0.01,
           "every": 100, "num_scans": 1, "source_scans": 100,
           "entries": [{"points": str(velo / "000000.bin"), "labels": str(lab / "000000.label")}]}
    path = root / "subset.json"
    path.write_text(json.dumps(doc))
    return str(path)


def _train_settings() -> str:
    s = section_defaults("downstream")
    s.update(device="cpu", voxel_size=0.8)
    s["schedule"].update(iterations=1, batch_size=2, warmup_iters=0, log_interval=1, checkpoint_interval=1)
    return json.dumps(s)


def test_train_segmentor_max_generated_uses_exactly_n_and_records_it(tmp_path, capsys):
    samples, pseudo = _shards(tmp_path, [[300, 0, 300], [300, 300, 300]])
    common = ["train-segmentor", "--backbone", "minkunet", "--subset", _subset(tmp_path),
              "--settings", _train_settings(), "--work-dir", str(tmp_path / "work"),
              "--samples", *map(str, samples), "--pseudo-labels", *map(str, pseudo), "--domains", "vehicle"]
    out = tmp_path / "gda4.pt"
    assert main([*common, "--max-generated", "4", "--out", str(out)]) == 0
    train = torch.load(out, weights_only=True)["train"]
    info = train["info"]
    assert info["role"] == "gda" and info["max_generated"] == 4 and info["empty_generated"] == 1
    assert train["num_generated"] == 3 and train["num_real"] == 1  # 4 taken, the empty one not trained on
    assert "first 4 scans" in info["generated_selection"]
    # More than the shards hold: one error line naming the shard, no checkpoint.
    capsys.readouterr()
    assert main([*common, "--max-generated", "7", "--out", str(tmp_path / "gda7.pt")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert len(err) == 1 and "shard_1" in err[0] and "fewer than the 7" in err[0]
    assert not (tmp_path / "gda7.pt").exists()


def _evaluation(path, role: str, max_generated, miou: float, train_seconds: float, num_generated: int = 0,
                seed: int = 0) -> str:
    """A hand-made evaluate-segmentor output (only the fields the curve reads)."""
    doc = {
        "checkpoint": str(path).replace(".val.json", ".pt"), "model": {"backbone": "minkunet"},
        "label_space": "semantickitti", "class_names": ["car"], "voxel_size": 0.3, "seed": seed, "seconds": 1.5,
        "train": {"seconds": train_seconds, "iterations": 40, "num_real": 2, "num_generated": num_generated,
                  "info": {"role": role, "dataset": "semantickitti", "percent": 1.0, "max_generated": max_generated,
                           "domains": ["vehicle"] if role == "gda" else []}},
        "sets": {"val": {"miou": miou, "miou_nanmean": miou + 0.05, "accuracy": 0.8, "iou": {}, "num_scans": 1}},
    }
    path.write_text(json.dumps(doc))
    return str(path)


@pytest.fixture
def curve_inputs(tmp_path):
    """Evaluations of 0, 2 and 4 generated scans, two 3-scan sample shards with their
    timing files (12 s and 6 s: 3 s per scan) and pseudo-label sidecars (0.2 s per scan)."""
    samples, pseudo = _shards(tmp_path, [[20, 20, 0], [20, 20, 20]])
    benches = []
    for k, seconds in enumerate((12.0, 6.0)):
        (samples[k] / "timing.json").write_text(json.dumps({"scans": 3, "seconds": seconds}))
        benches.append(str(samples[k] / "timing.json"))
        (pseudo[k] / "sidecar.json").write_text(json.dumps({
            "scans": [{"name": "x"}] * 3, "seconds": 0.6, "labeler": {"train": {"seconds": 30.0}}}))
    evals = [_evaluation(tmp_path / "gda4.val.json", "gda", 4, 0.30, 11.0, 3),
             _evaluation(tmp_path / "real.val.json", "supervised_only", None, 0.20, 10.0),
             _evaluation(tmp_path / "gda2.val.json", "gda", 2, 0.25, 10.5, 1)]
    return tmp_path, evals, samples, benches, pseudo


def _curve_args(root, evals, samples, benches, pseudo):
    return ["gda-curve", *DATA_SOURCE_ARGS, "--evaluations", *evals, "--samples", *map(str, samples),
            "--pseudo-labels", *map(str, pseudo), "--out", str(root / "curve.json"),
            "--figure", str(root / "curve.png")]


def test_gda_curve_rows_and_compute(curve_inputs):
    root, evals, samples, benches, pseudo = curve_inputs
    assert main(_curve_args(root, evals, samples, benches, pseudo)) == 0
    doc = read_curve(root / "curve.json")  # what sampler-tradeoff reads: passes its checks
    rows = doc["rows"]
    assert [r["generated_scans"] for r in rows] == [0, 2, 4]
    assert [r["miou"] for r in rows] == [0.20, 0.25, 0.30]
    assert [r["sampling_seconds"] for r in rows] == [0.0, 6.0, 12.0]  # N x 18 s / 6 scans
    assert [r["pseudo_label_seconds"] for r in rows] == [0.0, 0.4, 0.8]
    assert [r["train_seconds"] for r in rows] == [10.0, 10.5, 11.0]  # each run's own recorded time
    assert all(math.isclose(r["total_seconds"], r["train_seconds"] + r["sampling_seconds"]
                            + r["pseudo_label_seconds"]) for r in rows)
    assert rows[2]["trained_generated_scans"] == 3
    for key in ("experiment", "config_hash", "code_hash", "data_source", "device", "seeds", "timings"):
        assert key in doc
    assert doc["data_source"] == DATA_SOURCE
    assert doc["timings"]["sampling_per_scan"] == 3.0 and doc["timings"]["labeler"] == 30.0
    assert doc["setup"]["backbone"] == "minkunet" and doc["setup"]["domain"] == "vehicle"
    assert (root / "curve.png").stat().st_size > 1000


def test_gda_curve_over_seeds_gives_mean_and_error_bars(curve_inputs, capsys):
    root, evals, samples, benches, pseudo = curve_inputs
    extra = [_evaluation(root / "real_s1.val.json", "supervised_only", None, 0.24, 12.0, seed=1),
             _evaluation(root / "gda2_s1.val.json", "gda", 2, 0.21, 10.5, 1, seed=1),
             _evaluation(root / "gda4_s1.val.json", "gda", 4, 0.34, 13.0, 3, seed=1)]
    assert main(_curve_args(root, evals + extra, samples, benches, pseudo)) == 0
    rows = read_curve(root / "curve.json")["rows"]
    assert [r["seeds"] for r in rows] == [[0, 1]] * 3
    assert [r["miou_per_seed"] for r in rows] == [[0.20, 0.24], [0.25, 0.21], [0.30, 0.34]]
    assert [r["miou"] for r in rows] == pytest.approx([0.22, 0.23, 0.32])
    assert [r["miou_std"] for r in rows] == pytest.approx([0.02 * 2 ** 0.5] * 3)
    assert rows[0]["train_seconds"] == 11.0  # mean of the seeds' training seconds
    # A count that ran other seeds than the rest: one clear error.
    capsys.readouterr()
    assert main(_curve_args(root, evals + extra[:2], samples, benches, pseudo)) == 2
    assert "the counts ran different seeds" in capsys.readouterr().err


def test_gda_curve_bad_runs_are_input_errors(curve_inputs, capsys):
    root, evals, samples, benches, pseudo = curve_inputs
    full = _evaluation(root / "full.val.json", "gda", None, 0.3, 11.0, 5)  # a run without --max-generated
    twice = _evaluation(root / "again.val.json", "gda", 2, 0.3, 11.0, 1)
    for extra, message in ((full, "not a run trained with --max-generated"),
                           (twice, "a second run with 2 generated scans")):
        capsys.readouterr()
        assert main(_curve_args(root, [*evals, extra], samples, benches, pseudo)) == 2
        assert message in capsys.readouterr().err
    Path(benches[1]).write_text('{"scans": 3}')
    assert main(_curve_args(root, evals, samples, benches, pseudo)) == 2
    assert "timing.json: not a sample timing file" in capsys.readouterr().err
    assert not (root / "curve.json").exists()


GOOD_ROW = {"generated_scans": 4, "miou": 0.3, "train_seconds": 1.0, "sampling_seconds": 2.0, "total_seconds": 3.0}


@pytest.mark.parametrize("content, problem", [
    (None, "not found"),
    ("{not json", "invalid JSON"),
    (json.dumps({"rows": []}), "non-empty list 'rows'"),
    (json.dumps({"rows": [{k: v for k, v in GOOD_ROW.items() if k != "miou"}]}), "lacks miou"),
    (json.dumps({"rows": [{**GOOD_ROW, "total_seconds": float("nan")}]}), "total_seconds must be a finite number"),
    (json.dumps({"rows": [{**GOOD_ROW, "miou": 42.0}]}), "fraction in [0, 1]"),
    (json.dumps({"rows": [GOOD_ROW, GOOD_ROW]}), "two rows with 4 generated scans"),
])
def test_bad_curve_file_is_an_input_error(tmp_path, content, problem):
    path = tmp_path / "gda_curve.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(InputError, match=problem.replace("[", r"\[").replace("]", r"\]")) as err:
        read_curve(path)
    assert str(path) in str(err.value)


def test_sampler_tradeoff_puts_the_curve_rows_in_its_output(fixture_dir, tmp_path):
    """The sampler study (one setting, tiny untrained generator) with a hand-made curve file."""
    r = fixture_dir
    curve = tmp_path / "gda_curve.json"
    curve.write_text(json.dumps({"setup": {"backbone": "minkunet", "percent": 1.0}, "rows": [
        {**GOOD_ROW, "generated_scans": 8, "miou": 0.31, "total_seconds": 66.0},
        {**GOOD_ROW, "generated_scans": 0, "miou": 0.22, "total_seconds": 48.0}]}))
    settings = tradeoff_settings(tradeoff={"samplers": {"ddim": [1]}, "scans": 2, "domains": ["Vehicle"],
                                           "seed_groups": 1, "feature_metrics": ["FRID"]})
    rc = main(["sampler-tradeoff", *DATA_SOURCE_ARGS, "--domains", str(r / "index.json"), "--prompts", str(r / "prompts.pt"),
               "--checkpoint", str(r / "model.pt"), "--weights", f"frid={r / 'frid.pt'}", "--gda-curve", str(curve),
               "--settings", settings, "--out", str(tmp_path / "t.json"), "--figure", str(tmp_path / "t.png")])
    assert rc == 0
    t = json.loads((tmp_path / "t.json").read_text())
    # The rows, sorted by generated scans, become the downstream panel (mIoU vs total compute).
    assert [(d["generated_scans"], d["miou"], d["total_seconds"]) for d in t["downstream"]] == [
        (0, 0.22, 48.0), (8, 0.31, 66.0)]
    assert t["downstream_setup"]["source"] == str(curve) and t["downstream_setup"]["backbone"] == "minkunet"
    assert (tmp_path / "t.png").stat().st_size > 1000


def test_sampler_tradeoff_reads_the_curve_before_sampling(tmp_path, capsys):
    """A bad curve file stops the (long) sampler study at once: one line naming it, no output."""
    from omnilidar.commands.sampler_tradeoff import downstream_curve

    good = tmp_path / "good.json"
    good.write_text(json.dumps({"setup": {"backbone": "spvcnn"},
                                "rows": [{**GOOD_ROW, "generated_scans": 8}, {**GOOD_ROW, "generated_scans": 0}]}))
    rows, setup = downstream_curve(good)
    assert [r["generated_scans"] for r in rows] == [0, 8] and setup["backbone"] == "spvcnn"
    assert downstream_curve(None) == ([], None)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"rows": [{"generated_scans": 1}]}))
    code = main(["sampler-tradeoff", *DATA_SOURCE_ARGS, "--domains", "d.json", "--prompts", "p.pt", "--checkpoint", "m.pt",
                 "--gda-curve", str(bad), "--out", str(tmp_path / "t.json"), "--figure", str(tmp_path / "t.png")])
    err = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert code == 2 and len(err) == 1 and "bad.json: rows[0] lacks miou" in err[0]
    assert not (tmp_path / "t.json").exists()


def test_short_log_axes_get_few_readable_labels(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ticks = nice_log_ticks(0.21, 0.6)
    assert 2 <= len(ticks) <= 5 and all(0.21 <= t <= 0.6 for t in ticks)
    assert nice_log_ticks(0.2, 0.6) == [0.2, 0.3, 0.5]  # the coarsest round set with three ticks
    narrow = nice_log_ticks(1.01, 1.09)  # no two round numbers inside: three distinct values inside
    assert len(set(narrow)) == 3 and all(1.01 <= t <= 1.09 for t in narrow)
    # as many digits as needed; interior points, not the axis ends (their labels get clipped)
    assert tick_labels(nice_log_ticks(1.001, 1.0012)) == ["1.00105", "1.0011", "1.00115"]
    assert nice_log_ticks(50.4976, 63.1897) == [53.0, 56.0, 60.0]  # the GDA curve's compute axis
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0.21, 0.3, 0.45, 0.6], [1, 2, 3, 4], "o-")
    readable_log_x(ax)
    fig.canvas.draw()
    lo, hi = ax.get_xlim()
    major = [t.get_text() for t in ax.get_xticklabels() if t.get_text() and lo <= t.get_position()[0] <= hi]
    minor = [t.get_text() for t in ax.get_xticklabels(minor=True) if t.get_text()]
    assert 2 <= len(major) <= 5 and len(set(major)) == len(major) and minor == []
    assert all(len(s) <= 5 for s in major)  # plain numbers, e.g. 0.3, not 3x10^-1 strings
    # Labels do not overlap: their rendered extents are disjoint.
    boxes = sorted((t.get_window_extent() for t in ax.get_xticklabels()
                    if t.get_text() and lo <= t.get_position()[0] <= hi), key=lambda b: b.x0)
    assert all(a.x1 <= b.x0 for a, b in zip(boxes, boxes[1:]))
    plt.close(fig)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return copy_workflow(tmp_path_factory.mktemp("wf_gda_curve"))


def _trained_runs(text: str) -> set[str]:
    """Checkpoints the dry run plans to train (outputs of the training rules)."""
    runs, rule = set(), None
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("rule ") and line.endswith(":"):
            rule = line[5:-1]
        elif line.startswith("output:") and rule in ("train_supervised", "train_gda", "train_gda_curve"):
            runs.add(line.split("/")[-1])
    return runs


def test_curve_dag_trains_each_count_once_and_reuses_the_supervised_run(workdir):
    text = rerun_reasons(workdir, "results/gda_curve.json", "--configfile", TINY)
    # test.yaml: generated_scans [0, 1, 2]; 0 is the supervised-only run.
    assert _trained_runs(text) == {"minkunet_1pct_real.pt", "minkunet_1pct_gda1-vehicle.pt",
                                   "minkunet_1pct_gda2-vehicle.pt"}
    jobs = planned_jobs(workdir, "results/gda_curve.json", "results/semkitti_1pct.json", "--configfile", TINY)
    # With the semkitti target: still one supervised-only MinkUNet (shared), plus SPVCNN's.
    assert jobs["train_supervised"] == 2 and jobs["train_gda_curve"] == 2 and jobs["train_gda"] == 2
    assert jobs["gda_curve"] == 1 and jobs["sample_domain"] == 1


def test_curve_counts_are_capped_by_what_is_sampled_and_checked(workdir, tmp_path):
    cfg = yaml.safe_load((workdir / TINY).read_text())
    cfg["downstream"]["experiments"]["gda_curve"] = {"generated_scans": [0, 2, 5]}  # 5 > the 2 sampled
    capped = tmp_path / "capped.yaml"
    capped.write_text(yaml.safe_dump(cfg))
    text = rerun_reasons(workdir, "results/gda_curve.json", "--configfile", str(capped))
    assert _trained_runs(text) == {"minkunet_1pct_real.pt", "minkunet_1pct_gda2-vehicle.pt"}
    for bad, word in (({"generated_scans": [4], "typo": 1}, "typo"), ({"domain": "mars"}, "mars")):
        cfg["downstream"]["experiments"]["gda_curve"] = bad
        capped.write_text(yaml.safe_dump(cfg))
        out = snakemake(workdir, "--dry-run", "results/gda_curve.json", "--configfile", str(capped), check=False)
        assert out.returncode != 0 and word in out.stdout + out.stderr


def test_gda_curve_draws_real_series_beside_the_generated_one(curve_inputs, capsys):
    """--max-pool runs (real pool scans with true or the labeler's labels) become the curve's
    real_series, by N and seed, and the figure's extra lines."""
    root, evals, samples, benches, pseudo = curve_inputs

    def pool_run(name, role, n, miou, seed=0):
        path = _evaluation(root / name, role, None, miou, 9.0, n, seed=seed)
        doc = json.loads(Path(path).read_text())
        doc["train"]["info"]["max_pool"] = n
        Path(path).write_text(json.dumps(doc))
        return path

    real = [pool_run("t2.val.json", "real_truth", 2, 0.40), pool_run("t4.val.json", "real_truth", 4, 0.50),
            pool_run("p2.val.json", "real_pseudo", 2, 0.26), pool_run("p4.val.json", "real_pseudo", 4, 0.28)]
    assert main(_curve_args(root, evals + real, samples, benches, pseudo)) == 0
    doc = read_curve(root / "curve.json")
    assert [r["generated_scans"] for r in doc["rows"]] == [0, 2, 4]  # the generated curve is unchanged
    series = doc["real_series"]
    assert [(p["scans"], p["miou"]) for p in series["real_truth"]] == [(2, 0.40), (4, 0.50)]
    assert [p["miou"] for p in series["real_pseudo"]] == [0.26, 0.28]
    assert "real_truth: 2 scans 40.00, 4 scans 50.00" in capsys.readouterr().out
    # A run that is neither: one clear error.
    bad = pool_run("bad.val.json", "real_truth", 0, 0.1)
    assert main(_curve_args(root, evals + [bad], samples, benches, pseudo)) == 2


def test_curve_dag_trains_the_real_series_on_the_first_n_pool_scans(workdir):
    jobs = planned_jobs(workdir, "results/gda_curve.json")
    # Default counts 4, 8, 16; both real series; the pool (16 scans) made and labelled once.
    assert jobs["train_curve_pool"] == 6 and jobs["make_pool"] == jobs["pseudo_label_pool"] == 1
    out = snakemake(workdir, "--dry-run", "--printshellcmds", "results/gda_curve.json").stdout
    assert "--pool data/subsets/semantickitti_1pct_pool16.json  --max-pool 4" in out
    assert "--pool-labels data/pseudo_labels/pool/semantickitti_1pct_pool16 --max-pool 8" in out
    assert "minkunet_1pct_pool16-pseudo16.val.json" in next(
        line for line in out.splitlines() if "omnilidar gda-curve" in line)
