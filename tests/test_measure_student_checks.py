"""benchmarks/measure_student_checks.py on the student checks kept in docs/results: each domain's
excess over twice its spread is at most 1 exactly where the check says it held, and the figure is
written."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_a_domain_is_at_or_below_the_line_exactly_where_its_check_held(tmp_path):
    path = ROOT / "docs" / "results" / "student_1step_long_last_round_seed1.json"
    doc = json.loads(path.read_text())
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "measure_student_checks.py"), "--check",
                          f"seed 1={path}", "--out", str(tmp_path / "checks.png")],
                         capture_output=True, text=True, check=True).stdout
    for metric in ("JSD", "MMD"):
        per_domain = doc["student_check"]["metrics"][metric]["per_domain"]
        line = next(line for line in out.splitlines() if line.startswith(f"{metric} seed 1:"))
        assert f"held {sum(v['held'] for v in per_domain.values())}/{len(per_domain)}" in line
        for domain, v in per_domain.items():
            ratio = float(line.split(f" {domain} ")[1].split(",")[0])
            assert (ratio <= 1.0) == v["held"], (metric, domain, ratio)
    assert "held 5/8" in out  # seed 1's three JSD misses (docs/results.md, "A longer last round")
    assert (tmp_path / "checks.png").stat().st_size > 10_000
