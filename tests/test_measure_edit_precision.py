"""benchmarks/measure_edit_precision.py: how far SDEdited scans moved from their sources, in the
unit of sampling.range_noise; a shard without sources.json is one clear error."""

from __future__ import annotations

import json
import subprocess
import sys

from omnilidar.generator.checkpoint import load_generator
from omnilidar.generator.sampling import sample_shard
from test_carried_labels import _domain_shard
from test_generator_fixtures import one_torch_thread  # noqa: F401
from test_generator_sampling import model_files  # noqa: F401


def test_a_known_range_noise_is_measured_back_and_fresh_samples_are_refused(model_files, tmp_path):
    root, settings, cache = model_files
    files, _ = _domain_shard(tmp_path, settings, n=3)
    den, payload = load_generator(root / "ckpt.pt")
    base = dict(settings["sampling"], strength=0.001, keep_source=["intensity"])
    for name, noise in (("clean", 0.0), ("noisy", 0.03)):
        sample_shard(den, payload, cache, "Fog", 0, 3, dict(base, range_noise=noise), 5, tmp_path / name / "shard_0",
                     log=lambda *_: None, sources=files)
    out = tmp_path / "precision.json"
    cmd = [sys.executable, "benchmarks/measure_edit_precision.py", "--set", f"clean={tmp_path / 'clean'}",
           "--set", f"noisy={tmp_path / 'noisy'}", "--out", str(out)]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    figures = json.loads(out.read_text())["figures"]
    assert figures["clean"]["scans"] == figures["noisy"]["scans"] == 3
    assert figures["clean"]["encoded_std"] < 0.01  # strength 0.001 barely moves a scan
    assert abs(figures["noisy"]["encoded_std"] - 0.03) < 0.006 and figures["noisy"]["relative_median"] > 0.02
    sample_shard(den, payload, cache, "Fog", 0, 2, settings["sampling"], 5, tmp_path / "fresh" / "shard_0",
                 log=lambda *_: None)
    failed = subprocess.run([sys.executable, "benchmarks/measure_edit_precision.py", "--set", f"f={tmp_path / 'fresh'}"],
                            capture_output=True, text=True)
    assert failed.returncode != 0 and "no sources.json" in failed.stderr and "Traceback" not in failed.stderr
