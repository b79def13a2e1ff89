"""Sharded, resumable, batched sampling of range images and point clouds.

A shard is scans ``[shard * N, (shard + 1) * N)`` of one domain. Scan ``g`` (global
index) gets its own seed derived from (seed, crc32(domain name), g), and its own
torch generator for the initial noise and every ancestral step, so a scan's
result does not depend on the shard size, the batch size, or which scans were
already on disk. Each scan is written as

    DIR/range/%06d.npz       key "image": (2, H, W) float32 in [-1, 1]
    DIR/velodyne/%06d.bin    float32 x, y, z, intensity (SemanticKITTI layout)

named by its global index. With ``sampling.strength`` < 1 scan ``g`` is an SDEdit of one of the
domain's training scans (:func:`source_scans`), noised to t = strength and denoised (the channels
in ``sampling.keep_source`` then copied back from it), and ``DIR/sources.json`` names each scan's
training scan (what ``carry-labels`` reads). ``sampling.range_noise`` adds seeded noise of a known
size to every return's range after that (a diagnostic). Work goes
into ``DIR.partial``; scans already there are skipped (resume after interruption) when the
partial shard's ``PROVENANCE.json``
matches this job's (same checkpoint and prompt contents, settings, seed and code),
else it starts fresh; every file is written atomically, and only a complete shard
is renamed to ``DIR``.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import time
import zlib
from pathlib import Path

import numpy as np
import torch

from omnilidar.errors import InputError
from omnilidar.manifest import write_manifest
from omnilidar.generator.data import load_range_image, rng_for
from omnilidar.generator.diffusion import generate, scan_seed
from omnilidar.generator.schedule import CosineLogSNRSchedule


TIMING_FILE = "timing.json"
PROVENANCE_FILE = "PROVENANCE.json"
IMAGE_CHANNELS = ("range", "intensity")  # the (2, H, W) image's channels, as encode() writes them
SOURCES_FILE = "sources.json"  # strength < 1: each scan's training scan and the image geometry
RANGE_NOISE_STREAM = 0x52A6  # keeps sampling.range_noise's draws apart from the sampler's


def domain_points_spec(settings: dict, payload: dict, domain: str) -> RangeImageSpec:
    """The geometry a ``domain`` scan is back-projected with: its own sensor's (e.g. the pitched
    drone) when the checkpoint knows it, else the generator's; the image shape is the generator's."""
    from omnilidar.data.range_image import RangeImageSpec
    from omnilidar.generator.unet import range_image_spec

    spec = range_image_spec(settings)
    geometry = payload.get("domain_range_images", {}).get(domain)
    points_spec = RangeImageSpec(**geometry) if geometry else spec
    if points_spec.shape != spec.shape:
        raise InputError(None, f"domain {domain}: images are {points_spec.shape}, the generator makes {spec.shape}")
    return points_spec


def _save_npz_atomic(path: Path, image: np.ndarray) -> None:
    from omnilidar.io.atomic import write_bytes_atomic

    buf = io.BytesIO()
    np.savez_compressed(buf, image=image)
    write_bytes_atomic(path, buf.getvalue())


def _check_partial(partial: Path, provenance: dict | None, log) -> None:
    """Remove a partial shard that another job left (other checkpoint, settings, seed or
    code); stamp the partial shard with this job's provenance."""
    from omnilidar.checkpoints import provenance_differences

    stamp = partial / PROVENANCE_FILE
    if partial.exists():
        stored = json.loads(stamp.read_text()) if stamp.is_file() else None
        why = provenance_differences(stored, provenance) if provenance is not None else []
        if why:
            log(f"starting fresh: {partial} holds another job's scans: " + "; ".join(why))
            shutil.rmtree(partial)
    if provenance is not None and not stamp.is_file():
        partial.mkdir(parents=True, exist_ok=True)
        stamp.write_text(json.dumps(provenance, indent=1, sort_keys=True))


def add_range_noise(image: np.ndarray, spec, std: float, rng: np.random.Generator) -> None:
    """Add N(0, std) to the encoded log-range of every return of ``image`` (2, H, W), in place, clipped to
    [-1, 1]; empty pixels stay empty. ``sampling.range_noise``: a generator of known per-point range
    precision (std 0.01 is about 2.2 % of the range; ``encode`` maps log2(range + 1) to [-1, 1])."""
    from omnilidar.data.range_image import decode

    returns = decode(image, spec)[2]
    image[0][returns] = np.clip(image[0][returns] + std * rng.standard_normal(int(returns.sum())), -1.0, 1.0)


def read_sources(shard: str | Path) -> tuple[dict, list[tuple[str, Path, Path]]]:
    """An SDEdited shard's ``sources.json`` and, per scan, (name, its range image, its source's range
    image); one error naming the shard when it was not sampled with strength < 1, or naming a
    listed file that is missing."""
    shard = Path(shard)
    path = shard / SOURCES_FILE
    if not path.is_file():
        raise InputError(shard, f"has no {SOURCES_FILE}: only scans sampled with generator.sampling.strength < 1 "
                                "start from a training scan")
    doc = json.loads(path.read_text())
    scans = [(name, shard / "range" / f"{name}.npz", Path(source)) for name, source in sorted(doc["scans"].items())]
    for name, edit, source in scans:
        for f in (edit, source):
            if not f.is_file():
                raise InputError(f, f"scan {name} of {path} is missing")
    return doc, scans


def source_scans(files: list[Path], seed: int, domain: str, indices: list[int]) -> list[Path]:
    """The training scans that global scans ``indices`` of ``domain`` start from (strength < 1):
    a seeded permutation of the domain's scans, so that scans 0..len(files)-1 all differ."""
    order = rng_for(seed, zlib.crc32(domain.encode()), 1).permutation(len(files))
    return [files[order[g % len(files)]] for g in indices]


def student_sampling(sampling: dict, payload: dict, path: str | Path) -> dict:
    """The sampling settings for a checkpoint: a distilled student samples with the DDIM steps it
    was distilled for, and ``sampling.student`` asks for one."""
    student = payload.get("student")
    if sampling.get("student") and not student:
        raise InputError(path, "generator.sampling.student is set but this is not a distilled student "
                               "(make data/generator/<preset>/student.pt with distill_generator)")
    if not student:
        return sampling
    if sampling.get("strength", 1.0) < 1.0:
        raise InputError(path, "a distilled student samples its own few-step grid from noise; "
                               "generator.sampling.strength < 1 needs the trained generator")
    return {**sampling, "sampler": student["sampler"], "steps": int(student["steps"]), "ddim_eta": 0.0}


def sample_shard(
    denoiser: torch.nn.Module,
    payload: dict,
    prompt_cache: dict,
    domain: str,
    shard: int,
    scans_per_shard: int,
    sampling: dict,
    seed: int,
    out_dir: str | Path,
    log=print,
    provenance: dict | None = None,
    sources: list[Path] | None = None,
) -> dict:
    """Generate one shard into ``out_dir`` (via ``out_dir.partial``); return timing stats.

    ``provenance`` (:func:`omnilidar.checkpoints.job_provenance`) decides whether scans
    an interrupted run left in ``out_dir.partial`` are this job's to reuse. ``sources``: the
    domain's training scans, which ``sampling.strength`` < 1 starts from."""
    from omnilidar.data.range_image import decode, unproject
    from omnilidar.io.semantickitti import write_points

    settings = payload["config"]
    names = payload["domains"]
    if domain not in names:
        raise InputError(None, f"unknown domain {domain!r}; the generator knows {', '.join(names)}")
    if domain not in prompt_cache["domains"]:
        raise InputError(None, f"prompt cache has no prompts for domain {domain!r}")
    if int(prompt_cache["dim"]) != int(payload["text"]["dim"]):
        raise InputError(None, f"prompt cache is {prompt_cache['dim']}-d, the generator was trained on {payload['text']['dim']}-d")
    if shard < 0 or scans_per_shard < 1:
        raise InputError(None, f"need shard >= 0 and scans per shard >= 1, got {shard}, {scans_per_shard}")
    strength = float(sampling.get("strength", 1.0))
    kept = [IMAGE_CHANNELS.index(c) for c in sampling.get("keep_source", [])]
    range_noise = float(sampling.get("range_noise", 0.0))
    if kept and strength >= 1.0:
        raise InputError(None, "generator.sampling.keep_source copies channels from each scan's source scan, "
                               "which needs generator.sampling.strength < 1")
    if strength < 1.0 and not sources:
        raise InputError(None, f"generator.sampling.strength {strength} starts from the domain's training scans: "
                               "give the domains index (omnilidar sample --domains)")
    out_dir = Path(out_dir)
    if out_dir.exists():
        log(f"{out_dir} is complete; nothing to do")
        return {"generated": 0, "skipped": scans_per_shard, "seconds": 0.0}
    partial = out_dir.with_name(out_dir.name + ".partial")
    _check_partial(partial, provenance, log)
    (partial / "range").mkdir(parents=True, exist_ok=True)
    (partial / "velodyne").mkdir(parents=True, exist_ok=True)

    points_spec = domain_points_spec(settings, payload, domain)
    d = settings["diffusion"]
    schedule = CosineLogSNRSchedule(d["logsnr_min"], d["logsnr_max"])
    entry = prompt_cache["domains"][domain]
    tokens, mask = entry["tokens"][0], entry["mask"][0]  # inference uses the first prompt
    device = next(denoiser.parameters()).device
    bf16 = device.type == "cuda" and bool(settings["training"].get("bf16", False))

    first = shard * scans_per_shard
    todo = [
        g for g in range(first, first + scans_per_shard)
        if not ((partial / "range" / f"{g:06d}.npz").exists() and (partial / "velodyne" / f"{g:06d}.bin").exists())
    ]
    skipped = scans_per_shard - len(todo)
    if skipped:
        log(f"resuming {partial}: {skipped} scans already written")
    t0 = time.perf_counter()
    bs = int(sampling["batch_size"])
    for start in range(0, len(todo), bs):
        batch = todo[start : start + bs]
        init = None
        if strength < 1.0:
            init = torch.from_numpy(np.stack([load_range_image(f, points_spec.shape)
                                              for f in source_scans(sources, seed, domain, batch)]))
        images = generate(
            denoiser, names.index(domain), tokens, mask, [scan_seed(seed, domain, g) for g in batch],
            points_spec.shape, sampling["sampler"], sampling["steps"], schedule, sampling["ddim_eta"], bf16,
            init=init, strength=strength,
        ).numpy()
        if kept:  # the source's own values: only the other channel's edit differs from real
            images[:, kept] = init.numpy()[:, kept]
        for g, img in zip(batch, images):
            if not np.isfinite(img).all():  # cannot happen after clamp/nan_to_num; never write one
                raise RuntimeError(f"non-finite sample for scan {g}")
            if range_noise > 0:
                add_range_noise(img, points_spec, range_noise, rng_for(scan_seed(seed, domain, g), RANGE_NOISE_STREAM))
            rng, inten, valid = decode(img, points_spec)
            write_points(partial / "velodyne" / f"{g:06d}.bin", unproject(rng, inten, points_spec, mask=valid))
            _save_npz_atomic(partial / "range" / f"{g:06d}.npz", img.astype(np.float32))
        done = start + len(batch)
        elapsed = time.perf_counter() - t0
        eta = elapsed / done * (len(todo) - done)
        log(f"{domain} shard {shard}: {done}/{len(todo)} scans, {elapsed / done:.2f} s/scan, ETA {eta:.0f} s")
    seconds = time.perf_counter() - t0
    # What the shard cost (model loading excluded); downstream compute accounting reads it.
    timing = {"scans": len(todo), "resumed_scans": skipped, "seconds": seconds,
              "seconds_per_scan": seconds / len(todo) if todo else None, "device": str(device),
              "sampler": sampling["sampler"], "steps": int(sampling["steps"]), "strength": strength,
              "keep_source": list(sampling.get("keep_source", [])), "range_noise": range_noise,
              "batch_size": bs}
    (partial / TIMING_FILE).write_text(json.dumps(timing, indent=1))
    if strength < 1.0:  # what carry-labels needs to give each edited scan its source's labels
        from dataclasses import asdict

        shard_scans = list(range(first, first + scans_per_shard))
        (partial / SOURCES_FILE).write_text(json.dumps({
            "strength": strength, "range_image": asdict(points_spec),
            "scans": {f"{g:06d}": str(src) for g, src in zip(shard_scans, source_scans(sources, seed, domain, shard_scans))},
        }, indent=1))
    write_manifest(partial)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    os.replace(partial, out_dir)
    return {"generated": len(todo), "skipped": skipped, "seconds": seconds}
