"""omnilidar split-pi3det: deterministic train/val lists of a platform, by sequence."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnilidar.cli import main
from omnilidar.data.index import build_index
from omnilidar.lidar.scan import Boxes
from omnilidar.io import pi3det


def _platform(root: Path, sequences: list[str], frames: int = 2) -> Path:
    """drone/<seq>/velodyne/<frame>.bin and one unsplit info list, in a shuffled order."""
    infos = []
    for s in sequences:
        for f in range(frames):
            rel = f"drone/{s}/velodyne/{f:06d}.bin"
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            np.zeros((4, 4), np.float32).tofile(root / rel)
            boxes = Boxes(np.array([[10, 0, -1, 4, 2, 1.5, 0]], np.float32), np.array(["Car"]))
            infos.append(pi3det.make_info(f"{s}_{f:06d}", "Drone", rel, boxes))
    order = np.random.default_rng(3).permutation(len(infos))
    pi3det.write_infos(root / "drone" / "drone_infos_all.pkl", [infos[i] for i in order])
    return root


def test_split_is_by_sequence_deterministic_and_indexes(tmp_path, capsys):
    root = _platform(tmp_path / "pi3det", [f"seq_{i:02d}" for i in (4, 0, 6, 1, 5, 3, 2)])
    assert main(["split-pi3det", str(root), "--platform", "drone"]) == 0
    assert "drone val: 2 sequences (drone/seq_00, drone/seq_05)" in capsys.readouterr().out
    train = pi3det.read_infos(root / "drone" / "drone_infos_train.pkl")
    val = pi3det.read_infos(root / "drone" / "drone_infos_val.pkl")
    assert sorted({i["frame_id"][:6] for i in val}) == ["seq_00", "seq_05"]
    assert len(train) == 10 and len(val) == 4
    first = [(root / "drone" / f"drone_infos_{s}.pkl").read_bytes() for s in ("train", "val")]
    assert main(["split-pi3det", str(root), "--platform", "drone"]) == 2  # never overwrites silently
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert main(["split-pi3det", str(root), "--platform", "drone", "--overwrite"]) == 0
    assert [(root / "drone" / f"drone_infos_{s}.pkl").read_bytes() for s in ("train", "val")] == first
    splits = build_index("pi3det", root)["splits"]
    assert len(splits["drone_train"]) == 10 and len(splits["drone_val"]) == 4


def test_one_sequence_cannot_be_split(tmp_path, capsys):
    root = _platform(tmp_path / "pi3det", ["seq_00"])
    assert main(["split-pi3det", str(root), "--platform", "drone"]) == 2
    assert "one sequence (drone/seq_00)" in capsys.readouterr().err
    assert not (root / "drone" / "drone_infos_train.pkl").exists()
