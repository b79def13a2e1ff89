"""benchmarks/measure_denoising.py on a tiny trained generator: its reference (the domain's mean image)
is the pixel variance of the domain's own scans, and near t = 0 any generator recovers its input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import torch

from omnilidar.generator.text import build_prompt_cache
from omnilidar.generator.training import train_generator
from test_generator_fixtures import make_domains, one_torch_thread, tiny_settings  # noqa: F401
from test_generator_training import FakeEncoder


def test_denoising_is_measured_against_the_domains_mean_image(tmp_path):
    settings = tiny_settings()
    index = make_domains(tmp_path, settings)
    prompts = tmp_path / "prompts.pt"
    torch.save(build_prompt_cache(settings["prompts"], FakeEncoder()), prompts)
    train_generator(settings, index, prompts, tmp_path / "work", tmp_path / "gen" / "model.pt", seed=1)
    out = tmp_path / "denoising.json"
    subprocess.run([sys.executable, "benchmarks/measure_denoising.py", "--domains", str(index), "--prompts",
                    str(prompts), "--generator", str(tmp_path / "gen" / "model.pt"), "--domain", "Fog",
                    "--times", "0.001", "0.9", "--noise-seeds", "2", "--threads", "1", "--out", str(out),
                    "--figure", str(tmp_path / "bev.png")],
                   check=True, capture_output=True, text=True)
    doc = json.loads(out.read_text())
    assert (tmp_path / "bev.png").stat().st_size > 5_000  # a training scan beside the generator's sample
    images = np.stack([np.load(f)["image"] for f in sorted((tmp_path / "ri" / "Fog" / "shard0").glob("*.npz"))])
    assert doc["figures"]["scans"] == len(images) == 3
    per_channel = ((images - images.mean(0)) ** 2).mean(axis=(0, 2, 3))  # each channel against its own mean
    assert np.allclose(list(doc["figures"]["mean_image_mse"].values()), per_channel, rtol=1e-5)
    assert list(doc["figures"]["mean_image_mse"]) == ["range", "intensity"]
    for channel in ("range", "intensity"):
        ratios = doc["figures"]["generators"][0]["ratio_to_mean_image"][channel]
        assert len(ratios["0.9"]) == 2 and all(r > 0 for r in ratios["0.9"])
        assert max(ratios["0.001"]) < 0.05  # almost no noise: x0 is the input, far better than the mean
    assert doc["columns"] == ["generator", "iterations", "loss weighting", "prior", "channel", "t = 0.001", "t = 0.9"]
    assert [r["channel"] for r in doc["rows"]] == ["range", "intensity"]
    assert doc["rows"][0] == {**doc["rows"][0], "generator": "gen", "iterations": "3", "loss weighting": "min_snr",
                              "prior": "zero"}
