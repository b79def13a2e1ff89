"""Training, resuming, evaluating and pseudo-labelling with tiny models on tiny scans,
through the library and the CLI (real mmengine Runner, a few iterations)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from omnilidar.cli import main
from omnilidar.config import section_defaults
from omnilidar.downstream.seg.dataset import records_from_entries
from omnilidar.downstream.seg.evaluate import evaluate_records, load_segmentor
from omnilidar.downstream.seg.label_spaces import get_label_space
from omnilidar.downstream.seg.labeler import import_labeler, training_settings
from omnilidar.downstream.seg.pseudo_label import generated_records, pseudo_label_shard
from omnilidar.downstream.seg.training import train_segmentor
from omnilidar.io import semantickitti

SPACE = get_label_space("semantickitti")


def _scene(rng: np.random.Generator, n: int = 1200) -> tuple[np.ndarray, np.ndarray]:
    """Road (x < 0) and sidewalk (x > 0) ground, and a car-sized box of points."""
    ground = np.column_stack([rng.uniform(-15, 15, (n, 2)), rng.normal(-1.7, 0.02, n)])
    car = np.column_stack([rng.uniform(4, 8, n // 4), rng.uniform(-1, 1, n // 4), rng.uniform(-1.7, -0.2, n // 4)])
    xyz = np.concatenate([ground, car]).astype(np.float32)
    points = np.column_stack([xyz, rng.uniform(0, 1, len(xyz)).astype(np.float32)])
    labels = np.concatenate([np.where(ground[:, 0] < 0, 40, 48), np.full(len(car), 10)]).astype(np.uint16)
    return points, labels


def _write_sequence(root, count, seed):
    velo, lab = root / "velodyne", root / "labels"
    velo.mkdir(parents=True)
    lab.mkdir()
    rng = np.random.default_rng(seed)
    for i in range(count):
        pts, sem = _scene(rng)
        semantickitti.write_points(velo / f"{i:06d}.bin", pts)
        semantickitti.write_label(lab / f"{i:06d}.label", sem)
    return [{"points": str(velo / f"{i:06d}.bin"), "labels": str(lab / f"{i:06d}.label")} for i in range(count)]


def _settings(iterations=3):
    s = section_defaults("downstream")
    s["voxel_size"] = 0.8
    s["schedule"].update(iterations=iterations, batch_size=2, warmup_iters=1, log_interval=1, checkpoint_interval=2,
                         lr=0.05)
    return {k: s[k] for k in ("backend", "device", "voxel_size", "max_voxels", "models", "schedule",
                              "augmentation", "mixing")}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("seg")
    real = records_from_entries(_write_sequence(root / "train", 3, 0), "semantickitti")
    val = records_from_entries(_write_sequence(root / "val", 2, 1), "semantickitti")
    out = root / "minkunet.pt"
    summary = train_segmentor(_settings(), "minkunet", real, [], SPACE, out, root / "work", seed=0)
    return root, real, val, out, summary


def test_training_writes_a_weights_only_checkpoint(trained):
    root, real, val, out, summary = trained
    assert summary["iterations"] == 3 and summary["num_real"] == 3
    raw = torch.load(out, weights_only=True)
    assert raw["model"]["backbone"] == "minkunet" and raw["label_space"] == "semantickitti"
    assert all(torch.isfinite(v).all() for v in raw["state_dict"].values() if v.is_floating_point())
    # The work dir's resumable checkpoints are weights-only loadable too.
    last = (root / "work" / "last_checkpoint").read_text()
    assert last == "iter_3.pth"  # a bare name: a copied work dir reads its own checkpoint
    ckpt = torch.load(root / "work" / last, weights_only=True)
    assert ckpt["meta"]["iter"] == 3
    assert ckpt["meta"]["omnilidar"]["provenance"]["command"] == "train-segmentor"


def test_rerun_resumes_and_reproduces_the_weights(trained, tmp_path):
    root, real, val, out, summary = trained
    again = tmp_path / "again.pt"
    s2 = train_segmentor(_settings(), "minkunet", real, [], SPACE, again, root / "work", seed=0)
    assert s2["resumed_from"] == 3  # same job -> resumed from the finished state
    a = torch.load(out, weights_only=True)["state_dict"]
    b = torch.load(again, weights_only=True)["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_evaluation_predicts_every_point(trained):
    root, real, val, out, summary = trained
    model, payload = load_segmentor(out, device="cpu")
    scores = evaluate_records(model, val, SPACE, payload["voxel_size"])
    assert scores["num_points"] == sum(np.fromfile(r["points"], np.float32).size // 4 for r in val)
    assert 0.0 <= scores["miou"] <= scores["miou_nanmean"] <= 1.0
    assert np.array(scores["confusion"]).sum() == scores["num_points"]  # every point labelled in truth


def test_pseudo_labels_are_raw_ids_sharded_like_the_samples(trained, tmp_path):
    root, real, val, out, summary = trained
    samples = tmp_path / "samples" / "shard_0"
    (samples / "velodyne").mkdir(parents=True)
    rng = np.random.default_rng(5)
    for i in range(2):
        semantickitti.write_points(samples / "velodyne" / f"{i:06d}.bin", _scene(rng)[0])
    np.zeros((0, 4), np.float32).tofile(samples / "velodyne" / "000002.bin")  # an empty sample
    model, payload = load_segmentor(out, device="cpu")
    side = pseudo_label_shard(model, payload, samples, tmp_path / "pseudo" / "shard_0")
    assert [s["num_points"] for s in side["scans"]][2] == 0
    sem, _ = semantickitti.read_label(tmp_path / "pseudo" / "shard_0" / "labels" / "000000.label")
    assert set(np.unique(sem)) <= set(semantickitti.LEARNING_MAP_INV.values()) - {0}
    records, empty = generated_records([samples], [tmp_path / "pseudo" / "shard_0"])
    assert len(records) == 2 and empty == 1


def test_user_labeler_checkpoint_as_plain_state_dict(trained, tmp_path):
    root, real, val, out, summary = trained
    section = section_defaults("downstream")["labeler"]
    state = torch.load(out, weights_only=True)["state_dict"]
    torch.save(state, tmp_path / "user.pt")
    section["voxel_size"] = 0.8
    info = import_labeler(section, tmp_path / "user.pt", tmp_path / "labeler.pt")
    assert info["model"]["backbone"] == "minkunet"
    model, payload = load_segmentor(tmp_path / "labeler.pt", device="cpu")
    assert payload["voxel_size"] == 0.8
    # A state dict of another architecture is one clear error.
    section["model"]["width"] = "W32"
    with pytest.raises(Exception, match="do not fit minkunet W32"):
        import_labeler(section, tmp_path / "user.pt", tmp_path / "bad.pt")
    assert not (tmp_path / "bad.pt").exists()
    assert training_settings(section)["models"] == {"minkunet": section["model"]}


def _cli(capsys, *args):
    code = main(list(args))
    return code, capsys.readouterr().err


def test_cli_bad_input_is_one_line_and_leaves_nothing(trained, tmp_path, capsys):
    root, real, val, out, summary = trained
    (tmp_path / "corrupt.pt").write_bytes(b"\x00" * 64)
    code, err = _cli(capsys, "evaluate-segmentor", "--checkpoint", str(tmp_path / "corrupt.pt"), "--set",
                     f"val={root / 'val'}", "--out", str(tmp_path / "e.json"))
    lines = [line for line in err.splitlines() if "error" in line]
    assert code == 2 and len(lines) == 1 and "corrupt.pt" in lines[0]
    assert not (tmp_path / "e.json").exists()
    code, err = _cli(capsys, "pseudo-label", "--labeler", str(tmp_path / "missing.pt"), "--samples", str(tmp_path),
                     "--out", str(tmp_path / "p"))
    assert code == 2 and "missing.pt: segmentor checkpoint not found" in err
    assert not (tmp_path / "p").exists()
    # Evaluation through the CLI works on the good checkpoint.
    code, err = _cli(capsys, "evaluate-segmentor", "--checkpoint", str(out), "--set", f"val={root / 'val'}",
                     "--settings", json.dumps({"device": "cpu"}), "--out", str(tmp_path / "e.json"))
    assert code == 0, err
    doc = json.loads((tmp_path / "e.json").read_text())
    assert doc["sets"]["val"]["num_scans"] == 2 and len(doc["sets"]["val"]["iou"]) == 19


def test_learning_rate_warms_up_then_anneals_to_zero():
    from omnilidar.downstream.seg.training import learning_rate

    sched = {"lr": 0.1, "warmup_iters": 4, "warmup_start_factor": 0.1}
    assert learning_rate(0, 20, sched) == pytest.approx(0.01)
    assert learning_rate(2, 20, sched) == pytest.approx(0.055)
    assert learning_rate(4, 20, sched) == pytest.approx(0.1)
    assert learning_rate(12, 20, sched) == pytest.approx(0.05)
    assert learning_rate(20, 20, sched) == pytest.approx(0.0, abs=1e-12)
    # A longer run at the same iteration is earlier in its schedule.
    assert learning_rate(12, 40, sched) > learning_rate(12, 20, sched)


def test_changed_scan_contents_start_fresh_and_more_iterations_resume(tmp_path, capsys):
    """The records name the same files; only their contents change, which the input digest sees."""
    real = records_from_entries(_write_sequence(tmp_path / "train", 3, 0), "semantickitti")
    inputs = {"scans": tmp_path / "train"}
    work = tmp_path / "work"
    first = train_segmentor(_settings(), "minkunet", real, [], SPACE, tmp_path / "a.pt", work, seed=0, inputs=inputs)
    assert first["resumed_from"] == 0
    import shutil

    shutil.rmtree(tmp_path / "train")
    _write_sequence(tmp_path / "train", 3, 7)  # same names, other scans
    capsys.readouterr()
    second = train_segmentor(_settings(), "minkunet", real, [], SPACE, tmp_path / "b.pt", work, seed=0, inputs=inputs)
    log = capsys.readouterr().out
    assert second["resumed_from"] == 0 and "starting fresh" in log and "input contents changed: scans" in log
    a = torch.load(tmp_path / "a.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "b.pt", weights_only=True)["state_dict"]
    assert any(not torch.equal(a[k], b[k]) for k in a if a[k].is_floating_point())
    longer = train_segmentor(_settings(iterations=4), "minkunet", real, [], SPACE, tmp_path / "c.pt", work, seed=0,
                             inputs=inputs)
    assert longer["resumed_from"] == 3 and longer["iterations"] == 4
    assert "resuming at iteration 3" in capsys.readouterr().out


def test_fewer_iterations_than_the_work_dir_holds_train_afresh(tmp_path, capsys):
    """Lowering the schedule (as the embedded default did, 200 -> 120) must not resume a checkpoint
    that is already past the new end: the run starts over and its weights equal a fresh run's."""
    real = records_from_entries(_write_sequence(tmp_path / "train", 3, 0), "semantickitti")
    inputs = {"scans": tmp_path / "train"}
    train_segmentor(_settings(iterations=4), "minkunet", real, [], SPACE, tmp_path / "long.pt", tmp_path / "work",
                    seed=0, inputs=inputs)
    capsys.readouterr()
    shorter = train_segmentor(_settings(iterations=2), "minkunet", real, [], SPACE, tmp_path / "short.pt",
                              tmp_path / "work", seed=0, inputs=inputs)
    assert shorter["resumed_from"] == 0 and shorter["iterations"] == 2
    assert "past the 2 asked for" in capsys.readouterr().out
    fresh = train_segmentor(_settings(iterations=2), "minkunet", real, [], SPACE, tmp_path / "fresh.pt",
                            tmp_path / "work_fresh", seed=0, inputs=inputs)
    a = torch.load(tmp_path / "short.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "fresh.pt", weights_only=True)["state_dict"]
    assert fresh["resumed_from"] == 0 and all(torch.equal(a[k], b[k]) for k in a)


def test_evaluation_logs_progress_lines(trained, capsys):
    """Long evaluations report done/total, seconds per scan and an ETA in their logs."""
    root, real, val, out, summary = trained
    model, payload = load_segmentor(out, device="cpu")
    evaluate_records(model, val, SPACE, payload["voxel_size"])
    lines = [l for l in capsys.readouterr().out.splitlines() if l.startswith("evaluated scans:")]
    assert lines and lines[-1].startswith(f"evaluated scans: {len(val)}/{len(val)},") and "ETA 0 s" in lines[-1]
