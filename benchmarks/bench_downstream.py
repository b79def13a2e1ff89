"""Segmentation training speed and peak memory per backbone and sparse backend.

One training step = forward, cross-entropy, backward and SGD step on a batch of
real KITTI scans (kitti_object in OMNILIDAR_REAL_DATA, random train ids) at the
CPU default's voxel size (and the reference 0.05 m on CUDA). Each configuration
runs in its own process so that its peak memory (max RSS on CPU, max allocated
on CUDA) is its own. Prints the median step time, iterations per second, peak
memory and the SPVCNN / MinkUNet time ratio.

With ``--cpu-paths``, SPVCNN on the CPU four ways in one run: as the stages run it (freed memory
kept for reuse, sparse-product devoxelisation, corner rows read from the trunk's kernel maps),
with glibc's default allocator, with the eight gathers for devoxelisation, and with every corner
found by binary search; medians, peak memory and the ratios.

    python benchmarks/bench_downstream.py [--steps 5] [--width W16] [--voxel 0.3] [--batch 2] [--cpu-paths]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from real_samples import KITTI_SCANS, real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)
import bench_record  # noqa: E402


def one(backbone: str, backend: str, width: str, voxel: float, batch: int, steps: int, device: str,
        keep_freed: bool = True, gathers: bool = False, searched: bool = False) -> dict:
    import resource

    import numpy as np
    import torch

    from omnilidar.allocator import keep_freed_memory
    from omnilidar.segnets import spvcnn

    if keep_freed:  # as every `omnilidar` stage runs
        keep_freed_memory()
    if gathers:  # the devoxelisation other devices use
        spvcnn.devoxelize = spvcnn.devoxelize_by_gathers
    if searched:  # every corner and own voxel by binary search, not from the trunk's kernel maps
        spvcnn._neighbours = lambda x, stride: None
        spvcnn._own_rows = lambda x, batch, stride: None

    from omnilidar.downstream.seg.dataset import SegCollate
    from omnilidar.downstream.seg.models import build_segmentor, model_spec
    from omnilidar.io import semantickitti

    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    scans = [semantickitti.read_points(p) for p in real_files_or_exit(KITTI_SCANS)]
    items = [{"points": scans[i % len(scans)], "labels": rng.integers(0, 20, len(scans[i % len(scans)])).astype(np.uint8),
              "path": None, "draw": i} for i in range(batch)]
    batch_data = SegCollate(20, voxel, 80000, 0)(items)["batch"].to(device)
    spec = model_spec(backbone, {"width": width, "depth": 18}, 19)
    model = build_segmentor(spec, backend, device, torch.Generator().manual_seed(0)).to(device).train()
    opt = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9, nesterov=True)
    times = []
    for _ in range(steps + 1):  # the first step builds caches and is not counted
        if device == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        logits = model(batch_data)
        loss = torch.nn.functional.cross_entropy(logits, batch_data.point_targets, ignore_index=-1)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if device == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    med = float(np.median(times[1:]))
    peak = (torch.cuda.max_memory_allocated() / 2**20 if device == "cuda"
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    return {"backbone": backbone, "backend": model.backend, "voxels": int(batch_data.voxel_coords.shape[0]),
            "points": int(batch_data.point_coords.shape[0]), "median_s": med, "it_per_s": 1.0 / med,
            "peak_mib": peak}


def child(cfg: dict) -> dict | None:
    """One configuration in its own single-threaded process (its own peak memory)."""
    out = subprocess.run([sys.executable, __file__, "--child", json.dumps(cfg)], capture_output=True, text=True,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    if out.returncode:
        print(f"{cfg}: failed\n{out.stderr[-1500:]}")
        return None
    return json.loads(out.stdout.strip().splitlines()[-1])


def compare_cpu_paths(args) -> None:
    base = dict(backbone="spvcnn", backend="torch", width=args.width, voxel=args.voxel, batch=args.batch,
                steps=args.steps, device="cpu")
    ways = {"as the stages run": {}, "glibc default allocator": {"keep_freed": False},
            "eight gathers": {"gathers": True}, "corners searched": {"searched": True}}
    rows = {}
    for name, change in ways.items():
        row = child(base | change)
        if row is None:
            return
        rows[name] = row
        print(f"spvcnn {args.width} cpu, {name}: {row['voxels']} voxels, {row['points']} points, median step "
              f"{row['median_s']:.3f} s, peak {row['peak_mib']:.0f} MiB", flush=True)
    ref = rows["as the stages run"]["median_s"]
    for name in list(ways)[1:]:
        print(f"ratio {name} / as the stages run: {rows[name]['median_s'] / ref:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--width", default="W16")
    ap.add_argument("--voxel", type=float, default=0.3)
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--cpu-paths", action="store_true", help="SPVCNN's CPU allocator and devoxelisation compared")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    bench_record.out_arg(ap)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(one(**json.loads(args.child))))
        return
    real_files_or_exit(KITTI_SCANS)  # one line now, not one per child
    if args.cpu_paths:
        compare_cpu_paths(args)
        return
    import torch

    from omnilidar.errors import InputError
    from omnilidar.sparse.backend import resolve_backend

    device = "cuda" if torch.cuda.is_available() else "cpu"
    backends = ["torch"]
    try:
        resolve_backend("spconv", device)
        backends.append("spconv")
    except InputError as err:
        print(f"spconv backend skipped: {err}")
    voxels = [args.voxel] + ([0.05] if device == "cuda" else [])
    rows = []
    for voxel in voxels:
        for backend in backends:
            for backbone in ("minkunet", "spvcnn"):
                row = child(dict(backbone=backbone, backend=backend, width=args.width, voxel=voxel, batch=args.batch,
                                 steps=args.steps, device=device))
                if row is None:
                    continue
                row = row | {"voxel": voxel}
                rows.append(row)
                print(f"{device} {row['backbone']:8s} {row['backend']:6s} {args.width} voxel {voxel:.2f} m "
                      f"batch {args.batch}: {row['voxels']} voxels, {row['points']} points, median step "
                      f"{row['median_s']:.3f} s ({row['it_per_s']:.2f} it/s), peak {row['peak_mib']:.0f} MiB",
                      flush=True)
    table = []
    for voxel in voxels:
        for backend in backends:
            pair = {r["backbone"]: r for r in rows if r["voxel"] == voxel and r["backend"] == backend}
            if len(pair) == 2:
                print(f"ratio spvcnn/minkunet step time ({backend}, {voxel} m): "
                      f"{pair['spvcnn']['median_s'] / pair['minkunet']['median_s']:.2f}")
            for name, r in pair.items():
                ratio = (f" ({r['median_s'] / pair['minkunet']['median_s']:.1f}x MinkUNet)"
                         if name == "spvcnn" and "minkunet" in pair else "")
                table.append({"what": f"{'MinkUNet' if name == 'minkunet' else 'SPVCNN'} {args.width} training step "
                                      f"({device}, {backend} backend, batch {args.batch}, {voxel} m voxels, "
                                      f"{r['voxels'] / 1e3:.1f}k voxels)",
                              "median": f"{r['median_s']:.2f} s, peak {r['peak_mib']:.0f} MiB{ratio}"})
    bench_record.write(args.out, table, {"runs": rows, "steps": args.steps})


if __name__ == "__main__":
    main()
