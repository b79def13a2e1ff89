"""The CUDA paths, checked on a GPU machine: AMP training of the generator (bf16) and of a
segmentor (bf16, fp16 on GPUs without it) through the real mmengine trainers, and CPU/CUDA agreement of sampling
and of segmentation. Prints one line per check with its figures; exits 1 when one fails.

    python benchmarks/check_cuda_paths.py            # needs a CUDA device

Tiny models and scans (the paths, not the scale, are under test); the paper-scale
speed is benchmarks/bench_generator.py --paper --device cuda --bf16.
"""

from __future__ import annotations

import copy
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from omnilidar.config import section_defaults
from omnilidar.downstream.seg.dataset import records_from_entries
from omnilidar.downstream.seg.evaluate import evaluate_records, load_segmentor
from omnilidar.downstream.seg.label_spaces import get_label_space
from omnilidar.downstream.seg.training import amp_dtype, train_segmentor
from omnilidar.generator.checkpoint import load_generator
from omnilidar.generator.diffusion import generate
from omnilidar.generator.schedule import CosineLogSNRSchedule
from omnilidar.generator.training import train_generator
from omnilidar.io import semantickitti
from omnilidar.manifest import digest

FAILED = []


def report(name: str, ok: bool, **figures) -> None:
    print(f"{'ok  ' if ok else 'FAIL'} {name}: " + ", ".join(f"{k} {v}" for k, v in figures.items()), flush=True)
    if not ok:
        FAILED.append(name)


def _scans(folder: Path, count: int, seed: int) -> list[dict]:
    """Road/sidewalk ground and a car-sized box per scan, SemanticKITTI layout."""
    rng = np.random.default_rng(seed)
    (folder / "velodyne").mkdir(parents=True)
    (folder / "labels").mkdir()
    entries = []
    for i in range(count):
        n = 3000
        ground = np.column_stack([rng.uniform(-15, 15, (n, 2)), rng.normal(-1.7, 0.02, n)])
        car = np.column_stack([rng.uniform(4, 8, n // 4), rng.uniform(-1, 1, n // 4), rng.uniform(-1.7, -0.2, n // 4)])
        xyz = np.concatenate([ground, car]).astype(np.float32)
        pts = np.column_stack([xyz, rng.uniform(0, 1, len(xyz)).astype(np.float32)])
        sem = np.concatenate([np.where(ground[:, 0] < 0, 40, 48), np.full(len(car), 10)]).astype(np.uint32)
        semantickitti.write_points(folder / "velodyne" / f"{i:06d}.bin", pts)
        semantickitti.write_label(folder / "labels" / f"{i:06d}.label", sem)
        entries.append({"points": str(folder / "velodyne" / f"{i:06d}.bin"),
                        "labels": str(folder / "labels" / f"{i:06d}.label")})
    return entries


def check_segmentor(root: Path) -> None:
    space = get_label_space("semantickitti")
    real = records_from_entries(_scans(root / "train", 4, 0), "semantickitti")
    val = records_from_entries(_scans(root / "val", 2, 1), "semantickitti")
    s = section_defaults("downstream")
    s["voxel_size"] = 0.4
    s["schedule"].update(iterations=20, batch_size=2, warmup_iters=2, log_interval=5, checkpoint_interval=10, amp=True)
    settings = {k: s[k] for k in ("backend", "device", "voxel_size", "max_voxels", "max_points", "models", "schedule",
                                  "augmentation", "mixing")}
    for backbone in ("minkunet", "spvcnn"):
        settings["device"] = "cuda"
        out = root / f"{backbone}.pt"
        t0 = time.perf_counter()
        summary = train_segmentor(settings, backbone, real, [], space, out, root / f"work_{backbone}", seed=0,
                                  inputs={"train": root / "train"})
        seconds = time.perf_counter() - t0
        state = torch.load(out, weights_only=True)["state_dict"]
        finite = all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point())
        report(f"{backbone} {amp_dtype()} AMP training on CUDA", finite and summary["device"].startswith("cuda"),
               iterations=summary["iterations"], seconds=f"{seconds:.1f}", backend=summary["backend"])
        scores = {}
        for device in ("cpu", "cuda"):
            model, payload = load_segmentor(out, backend="torch", device=device)
            scores[device] = evaluate_records(model, val, space, payload["voxel_size"])
        a, b = np.array(scores["cpu"]["confusion"]), np.array(scores["cuda"]["confusion"])
        agree = 1.0 - np.abs(a - b).sum() / 2 / max(a.sum(), 1)
        report(f"{backbone} evaluation CPU vs CUDA (fp32)", agree > 0.999,
               miou_cpu=f"{scores['cpu']['miou']:.4f}", miou_cuda=f"{scores['cuda']['miou']:.4f}",
               same_predictions=f"{agree:.5f}")


def _tiny_generator_settings() -> dict:
    s = copy.deepcopy(section_defaults("generator"))
    s["range_image"].update(height=16, width=64)
    s["prompts"] = {"Vehicle": ["a clear vehicle scan"], "Fog": ["a foggy scan"]}
    s["model"].update(base_channels=8, channel_multipliers=[1, 2], num_res_blocks=1, cross_attention_levels=[1],
                      cdfm_levels=[1], attention_head_dim=8, dafs_embed_dim=8)
    s["model"]["mamba"].update(d_state=4, backend="mambapy")
    s["training"].update(batch_size=4, iterations=10, warmup_iters=1, checkpoint_interval=5, log_interval=5, bf16=True)
    return s


def check_generator(root: Path) -> None:
    settings = _tiny_generator_settings()
    rng = np.random.default_rng(0)
    index = {"domains": {}}
    for i, name in enumerate(("Vehicle", "Fog")):
        shard = root / "ri" / name
        shard.mkdir(parents=True)
        for k in range(6):
            img = np.clip(rng.normal(0.2 * i, 0.3, (2, 16, 64)), -1, 1).astype(np.float32)
            np.savez(shard / f"{k:06d}.npz", image=img)
        index["domains"][name] = {"id": i, "shards": [str(shard)], "shard_digests": [digest(shard)]}
    (root / "domains.json").write_text(json.dumps(index))
    g = torch.Generator().manual_seed(0)
    cache = {"format": "omnilidar-prompts/1", "encoder": "random", "model": "random", "dim": 12, "max_tokens": 5,
             "domains": {n: {"prompts": p, "tokens": torch.randn(len(p), 5, 12, generator=g),
                             "mask": torch.ones(len(p), 5, dtype=torch.bool)} for n, p in settings["prompts"].items()}}
    torch.save(cache, root / "prompts.pt")
    t0 = time.perf_counter()
    summary = train_generator(settings, root / "domains.json", root / "prompts.pt", root / "work_gen", root / "gen.pt")
    seconds = time.perf_counter() - t0
    den_cpu, payload = load_generator(root / "gen.pt", device="cpu")
    finite = all(torch.isfinite(v).all() for v in payload["state_dict"].values() if v.is_floating_point())
    report("generator bf16 AMP training on CUDA (AmpOptimWrapper, EMA)", finite, iterations=summary["iterations"],
           seconds=f"{seconds:.1f}")
    den_cuda, _ = load_generator(root / "gen.pt", device="cuda")
    tok, mask = cache["domains"]["Fog"]["tokens"][0], cache["domains"]["Fog"]["mask"][0]
    sched = CosineLogSNRSchedule(settings["diffusion"]["logsnr_min"], settings["diffusion"]["logsnr_max"])
    for sampler, steps in (("ddim", 10), ("dpmpp_2m", 10)):
        cpu = generate(den_cpu, 1, tok, mask, [1, 2], (16, 64), sampler, steps, sched)
        gpu = generate(den_cuda, 1, tok, mask, [1, 2], (16, 64), sampler, steps, sched)
        diff = float((cpu - gpu).abs().max())
        # The initial noise comes from per-device generators, so only deterministic samplers can
        # agree across devices if the noise agrees: report what the devices draw.
        same_noise = torch.equal(torch.randn(4, generator=torch.Generator().manual_seed(1)),
                                 torch.randn(4, generator=torch.Generator("cuda").manual_seed(1), device="cuda").cpu())
        report(f"sampling {sampler} x{steps} on CUDA", bool(torch.isfinite(gpu).all()),
               max_abs_diff_vs_cpu=f"{diff:.3g}", same_initial_noise_across_devices=same_noise)


def main() -> int:
    if not torch.cuda.is_available():
        print("no CUDA device: nothing to check")
        return 1
    print(f"torch {torch.__version__}, {torch.cuda.get_device_name(0)}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        check_segmentor(Path(tmp) / "seg")
        check_generator(Path(tmp) / "gen")
    return 1 if FAILED else 0


if __name__ == "__main__":
    sys.exit(main())
