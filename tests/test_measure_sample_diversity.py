"""benchmarks/measure_sample_diversity.py on sampled sets laid out as sample_eval writes them: a set
whose scans are all one scan has no between-scan distance, a set of distinct scans has some, and
each is measured against the domain's real scans."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from omnilidar.generator.data import read_domains_index
from omnilidar.generator.text import build_prompt_cache
from omnilidar.generator.training import train_generator
from test_generator_fixtures import TINY_DOMAINS, make_domains, one_torch_thread, tiny_settings  # noqa: F401
from test_generator_training import FakeEncoder

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _write_set(root: Path, domain: str, images: list[np.ndarray]) -> None:
    shard = root / domain / "shard_0" / "range"
    shard.mkdir(parents=True)
    for k, image in enumerate(images):
        np.savez(shard / f"{k:06d}.npz", image=image)


def test_alike_scans_have_no_between_scan_distance_and_distinct_ones_have_some(tmp_path):
    settings = tiny_settings()
    index = make_domains(tmp_path, settings, scans_per_domain=(5, 3, 4))
    prompts = tmp_path / "prompts.pt"
    torch.save(build_prompt_cache(settings["prompts"], FakeEncoder()), prompts)
    settings["training"]["iterations"] = 1
    train_generator(settings, index, prompts, tmp_path / "work", tmp_path / "model.pt", seed=1)
    domain = TINY_DOMAINS[0]
    scans = [np.load(f)["image"] for f in read_domains_index(index)[domain]["files"]]
    _write_set(tmp_path / "distinct", domain, scans[:4])
    _write_set(tmp_path / "alike", domain, [scans[0]] * 4)
    out = tmp_path / "diversity.json"
    subprocess.run([sys.executable, str(BENCHMARKS / "measure_sample_diversity.py"), "--domains", str(index),
                    "--generator", str(tmp_path / "model.pt"), "--only", domain, "--scans", "4",
                    "--set", f"distinct={tmp_path / 'distinct'}", "--set", f"alike={tmp_path / 'alike'}",
                    "--out", str(out)], check=True, capture_output=True, text=True)
    figures = json.loads(out.read_text())["figures"][domain]
    assert set(figures) == {"real", "distinct", "alike"}
    assert figures["alike"]["between_scans"] < 1e-9 < figures["distinct"]["between_scans"]
    assert figures["alike"]["to_real"] > 0.0 and figures["alike"]["scans"] == 4
    # the distinct set is the first real scans themselves: nearer the real set than one scan repeated
    assert figures["distinct"]["MMD"] < figures["alike"]["MMD"]
    missing = subprocess.run([sys.executable, str(BENCHMARKS / "measure_sample_diversity.py"), "--domains", str(index),
                              "--generator", str(tmp_path / "model.pt"), "--only", TINY_DOMAINS[1],
                              "--set", f"alike={tmp_path / 'alike'}"], capture_output=True, text=True)
    assert missing.returncode != 0 and "no sample shards" in missing.stderr
