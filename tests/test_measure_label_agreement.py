"""benchmarks/measure_label_agreement.py: a labeler's labels of SDEdited scans scored against the
labels carried from their sources, on the same scans."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from omnilidar.io.semantickitti import to_raw_ids, write_label, write_points


def _shard(root, truth_ids, label_ids):
    """One shard of one scan, its labels and its carried truth (training ids; 0 = unlabelled)."""
    n = len(truth_ids)
    points = np.zeros((n, 4), dtype=np.float32)
    points[:, 0] = np.arange(n)
    for folder in ("velodyne", "labels"):
        (root / "scans" / "shard_0" / folder).mkdir(parents=True, exist_ok=True)
    write_points(root / "scans" / "shard_0" / "velodyne" / "000000.bin", points)
    for name, ids in (("labels", label_ids), ("truth", truth_ids)):
        (root / name / "shard_0" / "labels").mkdir(parents=True, exist_ok=True)
        write_label(root / name / "shard_0" / "labels" / "000000.label", to_raw_ids(np.asarray(ids, dtype=np.uint8)))
    (root / "truth" / "shard_0" / "sidecar.json").write_text(json.dumps({"samples": str(root / "scans" / "shard_0")}))


def test_labels_are_scored_against_the_carried_truth_of_the_same_scans(tmp_path):
    # car is training id 1, road 9: 4 car points, one called road; 3 road points; one unlabelled point ignored
    _shard(tmp_path, [1, 1, 1, 1, 9, 9, 9, 0], [1, 1, 1, 9, 9, 9, 9, 1])
    out = tmp_path / "agreement.json"
    cmd = [sys.executable, "benchmarks/measure_label_agreement.py", "--set",
           "=".join(["a set", *(str(tmp_path / d) for d in ("scans", "labels", "truth"))]), "--out", str(out)]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    row = json.loads(out.read_text())["rows"][0]
    assert row["accuracy"] == "85.7 %" and row["car IoU"] == "75.0" and row["road IoU"] == "75.0"
    assert row["mIoU"] == f"{100 * 1.5 / 19:.2f}"  # semantic-kitti-api: absent classes count as 0
    # Truth carried onto another scan is refused, naming the scan.
    other = tmp_path / "other"
    (other / "velodyne").mkdir(parents=True)
    write_points(other / "velodyne" / "000000.bin", np.ones((8, 4), dtype=np.float32))
    (tmp_path / "truth" / "shard_0" / "sidecar.json").write_text(json.dumps({"samples": str(other)}))
    failed = subprocess.run(cmd, capture_output=True, text=True)
    assert failed.returncode != 0 and "the truth was carried onto another scan" in failed.stderr
    assert "shard_0/velodyne/000000.bin" in failed.stderr and "Traceback" not in failed.stderr
