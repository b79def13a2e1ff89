"""benchmarks/measure_student_returns.py on a tiny trained generator and a student of it: a returns
fraction counts the pixels that decode to a valid range, so an x0 blurred between a missing return
(-1) and a return counts as a point once it passes the encoded minimum range."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from omnilidar.data.range_image import decode, encoded_min_range
from omnilidar.generator.text import build_prompt_cache
from omnilidar.generator.training import train_generator
from omnilidar.generator.unet import range_image_spec
from test_generator_fixtures import make_domains, one_torch_thread, tiny_settings  # noqa: F401
from test_generator_training import FakeEncoder

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))
from measure_student_returns import returns_fraction, row_range_spread  # noqa: E402


def test_a_blurred_pixel_counts_as_a_return_once_past_the_encoded_minimum_range():
    spec = range_image_spec(tiny_settings())
    floor = encoded_min_range(spec)
    image = np.full((2, *spec.shape), -1.0, np.float32)  # no returns at all
    assert returns_fraction(image, spec) == 0.0
    image[0, 0, :4] = [0.2, floor + 0.05, floor - 0.05, -0.99]  # a return, a blur above and below the floor
    assert returns_fraction(image, spec) == 2 / image[0].size


def test_a_row_range_spread_is_the_spread_of_one_row_s_returns_averaged_over_rows():
    spec = range_image_spec(tiny_settings())
    image = np.full((2, *spec.shape), -1.0, np.float32)
    image[0, 0, :2] = 0.5  # one row, two returns at one range: no spread
    assert row_range_spread(image, spec) == 0.0
    image[0, 1, :2] = [0.3, 0.7]  # another row, two ranges apart: its std is half their distance
    ranges = decode(image, spec)[0][1, :2]
    assert np.isclose(row_range_spread(image, spec), abs(ranges[1] - ranges[0]) / 4, rtol=1e-5)


def test_the_generator_and_its_student_are_counted_per_domain(tmp_path):
    settings = tiny_settings()
    settings["distillation"].update(teacher_steps=2, rounds=1, iterations_per_round=1)
    index = make_domains(tmp_path, settings)
    prompts = tmp_path / "prompts.pt"
    torch.save(build_prompt_cache(settings["prompts"], FakeEncoder()), prompts)
    train_generator(settings, index, prompts, tmp_path / "work", tmp_path / "model.pt", seed=1)
    train_generator(copy.deepcopy(settings), index, prompts, tmp_path / "swork", tmp_path / "student.pt", seed=1,
                    teacher=tmp_path / "model.pt")
    out = tmp_path / "returns.json"
    subprocess.run([sys.executable, str(BENCHMARKS / "measure_student_returns.py"), "--domains", str(index), "--prompts",
                    str(prompts), "--generator", str(tmp_path / "model.pt"), "--student", str(tmp_path / "student.pt"),
                    "--only", "Beam32", "--scans", "2", "--batch", "2", "--out", str(out)],
                   check=True, capture_output=True, text=True)
    figures = json.loads(out.read_text())["figures"]["Beam32"]
    assert set(figures) == {"training scans", "generator dpmpp_2m x 3", "student ddim x 1"}
    assert len(figures["generator dpmpp_2m x 3"]["returns"]) == 2 and len(figures["training scans"]["returns"]) > 2
    assert all(0.0 <= f <= 1.0 for values in figures.values() for f in values["returns"])
    assert all(s >= 0.0 for values in figures.values() for s in values["row_range_spread_m"])
    assert any(s > 0.0 for s in figures["training scans"]["row_range_spread_m"])
