"""benchmarks/measure_label_shares.py: each class's share of the points and mean remission, read from
sample shards and a round-tripped pool with their labels at the same relative paths."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from omnilidar.io.semantickitti import write_label, write_points, to_raw_ids


def _scan(root, rel, train_ids, remission):
    """One scan of len(train_ids) points with those labels (training ids) and remission."""
    n = len(train_ids)
    points = np.zeros((n, 4), dtype=np.float32)
    points[:, 0] = np.arange(n)
    points[:, 3] = remission
    (root / "scans" / rel / "velodyne").mkdir(parents=True, exist_ok=True)
    (root / "labels" / rel / "labels").mkdir(parents=True, exist_ok=True)
    write_points(root / "scans" / rel / "velodyne" / "000000.bin", points)
    write_label(root / "labels" / rel / "labels" / "000000.label", to_raw_ids(np.asarray(train_ids, dtype=np.uint8)))


def test_shares_and_remission_per_class_and_a_missing_label_is_an_error(tmp_path):
    # car is training id 1, road 9: shard 0 holds 3 car points (remission 0.1), shard 1 one road point (0.5)
    _scan(tmp_path, "shard_0", [1, 1, 1], 0.1)
    _scan(tmp_path, "shard_1", [9], 0.5)
    out = tmp_path / "shares.json"
    cmd = [sys.executable, "benchmarks/measure_label_shares.py",
           "--set", "a set=" + str(tmp_path / "scans") + "=" + str(tmp_path / "labels"), "--out", str(out)]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    rows = {r["class"]: r["a set"] for r in json.loads(out.read_text())["rows"]}
    assert rows == {"car": "75.0 (0.10)", "road": "25.0 (0.50)"}
    (tmp_path / "labels" / "shard_1" / "labels" / "000000.label").unlink()
    failed = subprocess.run(cmd, capture_output=True, text=True)
    assert failed.returncode != 0 and "no pseudo-labels for this scan" in failed.stderr
    assert "shard_1/labels/000000.label" in failed.stderr and "Traceback" not in failed.stderr
