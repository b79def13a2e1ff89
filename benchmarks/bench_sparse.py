"""Training speed and peak memory of the segmentation backbones per sparse backend.

One training iteration = voxelise nothing (done once), forward, cross-entropy,
backward, SGD step; kernel maps are rebuilt every iteration as they are for a
new scan. Input: the real SemanticKITTI scan 00/000000 from OMNILIDAR_REAL_DATA,
voxelised at 0.05 m and capped at 80k voxels (the reference training setting),
with random labels. Each (backbone, backend) runs in its own subprocess so that
``ru_maxrss`` is that configuration's peak resident memory.

    python benchmarks/bench_sparse.py                      # W32, full scan
    python benchmarks/bench_sparse.py --width W16 --crop 15 --iters 3

Prints the median seconds per iteration, iterations per second, peak RSS, the
ratio to the torch backend, and the backend that "auto" should use on this CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from real_samples import SEMANTICKITTI_SCAN, real_files_or_exit  # noqa: E402  (OMNILIDAR_REAL_DATA)
BACKBONES = ("minkunet", "spvcnn")
BACKENDS = ("torch", "spconv")


def one(args) -> dict:
    """Benchmark one configuration in this process; return a result dict."""
    import numpy as np
    import torch

    from omnilidar.segnets.minkunet import MinkUNet
    from omnilidar.segnets.spvcnn import SPVCNN
    from omnilidar.segnets.voxelize import IGNORE_INDEX, collate
    from omnilidar.io.semantickitti import read_points

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.backend == "spconv":
        from omnilidar.sparse import spconv_backend

        problem = spconv_backend.self_check("cpu")
        if problem is not None:
            return {"status": f"refused: {problem}"}
    points = read_points(real_files_or_exit(SEMANTICKITTI_SCAN)[0])
    if args.crop:
        points = points[(abs(points[:, 0]) < args.crop) & (abs(points[:, 1]) < args.crop)]
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 20, len(points))
    batch = collate([points] * args.batch, [labels] * args.batch, max_voxels=args.max_voxels, rng=rng)
    cls = MinkUNet if args.backbone == "minkunet" else SPVCNN
    model = cls(width=args.width, backend=args.backend, generator=torch.Generator().manual_seed(0))
    opt = torch.optim.SGD(model.parameters(), lr=0.24, momentum=0.9, nesterov=True, weight_decay=1e-4)
    times = []
    for it in range(args.iters + 1):  # the first iteration is warm-up
        t0 = time.perf_counter()
        logits = model(batch)
        loss = torch.nn.functional.cross_entropy(logits, batch.point_targets, ignore_index=IGNORE_INDEX)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if it:
            times.append(time.perf_counter() - t0)
    if not torch.isfinite(loss):
        return {"status": "non-finite loss"}
    return {
        "status": "ok",
        "voxels": int(batch.voxel_coords.shape[0]),
        "points": int(batch.point_coords.shape[0]),
        "median_s": statistics.median(times),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "threads": torch.get_num_threads(),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--width", default="W32", choices=["W16", "W20", "W32"])
    p.add_argument("--iters", type=int, default=5)
    p.add_argument("--batch", type=int, default=1, help="scans per iteration")
    p.add_argument("--max-voxels", type=int, default=80000)
    p.add_argument("--crop", type=float, default=0.0, help="keep |x|,|y| < CROP metres (0: whole scan)")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    p.add_argument("--one", nargs=2, metavar=("BACKBONE", "BACKEND"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one:
        args.backbone, args.backend = args.one
        print(json.dumps(one(args)))
        return

    real_files_or_exit(SEMANTICKITTI_SCAN)  # one line now, not one per child
    forwarded = [a for a in sys.argv[1:]]
    results = {}
    for backbone in BACKBONES:
        for backend in BACKENDS:
            proc = subprocess.run(
                [sys.executable, __file__, *forwarded, "--one", backbone, backend],
                capture_output=True, text=True, env={**os.environ, "PYTHONWARNINGS": "ignore"},
            )
            lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
            results[backbone, backend] = json.loads(lines[-1]) if lines else {
                "status": f"failed: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode}"}

    print(f"width {args.width}, {args.iters} timed iterations (median), batch {args.batch}, "
          f"max voxels {args.max_voxels}, crop {args.crop or 'none'}")
    print(f"{'backbone':10s} {'backend':8s} {'voxels':>7s} {'s/iter':>8s} {'iter/s':>7s} {'peak MB':>8s} "
          f"{'vs torch':>8s}  status")
    for (backbone, backend), r in results.items():
        if r["status"] != "ok":
            print(f"{backbone:10s} {backend:8s} {'':>7s} {'':>8s} {'':>7s} {'':>8s} {'':>8s}  {r['status']}")
            continue
        base = results[backbone, "torch"]
        ratio = base["median_s"] / r["median_s"] if base.get("status") == "ok" else float("nan")
        print(f"{backbone:10s} {backend:8s} {r['voxels']:7d} {r['median_s']:8.2f} {1 / r['median_s']:7.3f} "
              f"{r['peak_rss_mb']:8.0f} {ratio:7.2f}x  ok ({r['threads']} threads)")
    usable = {b: [r["median_s"] for (bb, be), r in results.items() if be == b and r["status"] == "ok"]
              for b in BACKENDS}
    usable = {b: sum(v) for b, v in usable.items() if len(v) == len(BACKBONES)}
    if usable:
        print(f"CPU default (fastest correct backend over both backbones): {min(usable, key=usable.get)}")
    else:
        print("no backend completed")


if __name__ == "__main__":
    main()
