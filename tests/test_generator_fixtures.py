"""Shared helpers for the generator tests (tiny range images, configs, domain indexes).

No tests here; the other test_generator_* modules import these helpers.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np

from omnilidar.config import section_defaults
from omnilidar.manifest import digest

TINY_DOMAINS = ("Vehicle", "Fog", "Beam32")


def tiny_settings(**training) -> dict:
    """A generator section small enough for unit tests (16 x 64 images, ~50 k parameters)."""
    s = copy.deepcopy(section_defaults("generator"))
    s["range_image"].update(height=16, width=64)
    s["prompts"] = {
        "Vehicle": ["a clear vehicle scan", "a car lidar sweep"],
        "Fog": ["a foggy scan with near clutter"],
        "Beam32": ["a sparse 32-beam scan", "half the beams missing", "low resolution lidar"],
    }
    s["model"].update(
        base_channels=8, channel_multipliers=[1, 2], num_res_blocks=1, cross_attention_levels=[1],
        cdfm_levels=[1], attention_head_dim=8, dafs_embed_dim=8,
    )
    s["model"]["mamba"].update(d_state=4, backend="mambapy")
    s["training"].update(
        batch_size=4, iterations=3, warmup_iters=1, checkpoint_interval=2, log_interval=1, ema_decay=0.9,
        **{"ema_warmup": 0, **training},  # no warm-up unless a test asks for it
    )
    s["sampling"].update(steps=3, batch_size=2, scans_per_shard=3)
    return s


def geometric_image(rng: np.random.Generator, h: int, w: int, kind: int) -> np.ndarray:
    """A simple (2, H, W) range image: ground-like rows, a box, and missing pixels (-1)."""
    rows = np.linspace(0.9, -0.3, h)[:, None] * np.ones((1, w))
    img = np.stack([rows, np.full((h, w), 0.2 * kind - 0.5)]).astype(np.float32)
    c = rng.integers(0, w - 8)
    img[0, h // 3 : h // 2, c : c + 8] = -0.2
    miss = rng.random((h, w)) < 0.1 + 0.1 * kind
    if kind == 2:
        miss[1::2] = True  # Beam32-like: every other row empty
    img[:, miss] = -1.0
    return np.clip(img + 0.01 * rng.standard_normal(img.shape).astype(np.float32), -1, 1)


def make_domains(root: Path, settings: dict, scans_per_domain=(5, 3, 4), seed: int = 0) -> Path:
    """Write tiny range-image shards + a domains index under ``root``; return the index path."""
    rng = np.random.default_rng(seed)
    h, w = settings["range_image"]["height"], settings["range_image"]["width"]
    index = {"domains": {}}
    for i, (name, n) in enumerate(zip(TINY_DOMAINS, scans_per_domain)):
        shard = root / "ri" / name / "shard0"
        shard.mkdir(parents=True, exist_ok=True)
        for k in range(n):
            np.savez(shard / f"{k:06d}.npz", image=geometric_image(rng, h, w, i))
        # Content digests of the shards, as the domain builder's index records them.
        index["domains"][name] = {"id": i, "shards": [str(shard)], "shard_digests": [digest(shard)]}
    path = root / "domains.json"
    path.write_text(json.dumps(index))
    return path


import pytest  # noqa: E402
import torch  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Tiny models run fastest single-threaded (and do not stall on a busy 2-core machine)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
