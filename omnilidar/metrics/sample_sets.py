"""Generated scan sets read from sample shards (``omnilidar sample`` output) for the
generation tables, so that the workflow samples at scale in parallel shard jobs and the
tables only score. A set is named on the command line as ``KEY=SHARD_DIR``, repeated
for each shard of the set, in shard order."""

from __future__ import annotations

import json
from pathlib import Path

from omnilidar.errors import InputError


def sample_set_arg(parser) -> None:
    parser.add_argument("--samples", action="append", default=[], metavar="KEY=SHARD_DIR",
                        help="a sample shard of one generated set (repeat per shard, in order); sets given "
                             "here are read instead of sampled")


def parse_sample_sets(pairs: list[str]) -> dict[str, list[Path]]:
    """{key: [shard dirs in the order given]} of ``--samples KEY=DIR`` arguments."""
    sets: dict[str, list[Path]] = {}
    for pair in pairs:
        key, sep, path = pair.partition("=")
        if not sep or not key or not path:
            raise InputError(None, f"--samples {pair!r}: expected KEY=SHARD_DIR")
        sets.setdefault(key, []).append(Path(path))
    return sets


def load_sample_set(shards: list[Path], count: int, key: str):
    """The first ``count`` range images of a set's shards, (count, 2, H, W), and the seconds
    per scan their sampling took (from each shard's timing.json; None when none recorded)."""
    import numpy as np

    files, seconds, scans = [], 0.0, 0
    for shard in shards:
        if not (shard / "range").is_dir():
            raise InputError(shard, f"sample set {key}: not a sample shard (no range/ folder)")
        files += sorted((shard / "range").glob("*.npz"))
        timing = shard / "timing.json"
        if timing.is_file():
            t = json.loads(timing.read_text())
            if t.get("scans"):
                seconds, scans = seconds + float(t["seconds"]), scans + int(t["scans"])
    if len(files) < count:
        raise InputError(shards[-1], f"sample set {key}: {len(files)} scans in its shards, {count} needed")
    images = np.stack([np.load(f)["image"].astype(np.float32) for f in files[:count]])
    return images, (seconds / scans if scans else None)


def generated_set(sets: dict[str, list[Path]], key: str, denoiser, payload: dict, prompt_cache: dict, domain: str,
                  count: int, sampler: str, steps: int, seed: int, batch_size: int):
    """Set ``key`` from its sample shards when given, else sampled here (small sets, runs by hand)."""
    if key in sets:
        return load_sample_set(sets[key], count, key)
    from omnilidar.metrics.generation import sample_images

    return sample_images(denoiser, payload, prompt_cache, domain, count, sampler, steps, seed, batch_size)
