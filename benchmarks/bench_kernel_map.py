"""Submanifold kernel maps: omnilidar.sparse against the plain per-offset search.

    python benchmarks/bench_kernel_map.py [--voxels 30000 50000] [--repeats 7]

Voxel sets shaped like a LiDAR sweep at 0.1 m on the Pi3DET grid (41 x 1504 x 752 cells, two
frames: rings of returns on a ground plane with some height jitter), in random row order as the
voxeliser leaves them. The plain search packs every row's 27 neighbours and binary-searches them
in a sorted key table, offset by offset; submanifold_map searches half the offsets (the other half
are their mirror images), in key order, one binary search per minor-axis column. Checks that both
give the same pairs in the same order, then prints median milliseconds and the ratio.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

import bench_record
from omnilidar.sparse.kernel_map import KernelMap, KeyTable, kernel_offsets, submanifold_map
from omnilidar.sparse.tensor import pack_coords

SHAPE = (41, 1504, 752)


def sweep_voxels(count: int, seed: int) -> torch.Tensor:
    """About ``count`` distinct (batch, z, y, x) voxels of two ring-pattern sweeps."""
    g = torch.Generator().manual_seed(seed)
    rows = []
    for b in range(2):
        n = count // 2 * 3
        ring = torch.randint(0, 64, (n,), generator=g).float()
        radius = 3.0 + ring ** 1.6 * 0.12
        angle = torch.rand(n, generator=g) * torch.pi - torch.pi / 2
        x = (radius * torch.cos(angle) / 0.1).long()
        y = (radius * torch.sin(angle) / 0.1 + SHAPE[1] / 2).long()
        z = (13 + torch.randn(n, generator=g) * 1.5).long()
        cells = torch.stack([torch.full_like(x, b), z, y, x], 1)
        inside = ((cells[:, 1:] >= 0) & (cells[:, 1:] < torch.tensor(SHAPE))).all(1)
        rows.append(torch.unique(cells[inside], dim=0)[: count // 2])
    coords = torch.cat(rows)
    return coords[torch.randperm(len(coords), generator=g)].int()


def plain_map(coords: torch.Tensor, shape=SHAPE) -> KernelMap:
    """Every offset searched on its own: the reference the benchmark compares against."""
    c = coords.long()
    n = len(c)
    offs = kernel_offsets(3) - 1
    table = KeyTable(pack_coords(c, shape))
    rows = torch.arange(n)
    ins, outs = [], []
    for off in offs:
        q = c[:, 1:] + off
        inside = ((q >= 0) & (q < torch.tensor(shape))).all(1)
        found = table.find(pack_coords(torch.cat([c[:, :1], q], 1).clamp(min=0), shape))
        valid = inside & (found >= 0)
        ins.append(found[valid])
        outs.append(rows[valid])
    counts = [0] + torch.cumsum(torch.tensor([len(i) for i in ins]), 0).tolist()
    return KernelMap(torch.cat(ins), torch.cat(outs), tuple(counts), n, n, len(offs) // 2)


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return round(statistics.median(times) * 1e3, 2)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--voxels", type=int, nargs="+", default=[30000, 50000])
    parser.add_argument("--repeats", type=int, default=7)
    bench_record.out_arg(parser)
    args = parser.parse_args()
    torch.set_num_threads(1)
    out = []
    for count in args.voxels:
        coords = sweep_voxels(count, seed=count)
        ours, ref = submanifold_map(coords, SHAPE), plain_map(coords)
        same = (torch.equal(ours.in_idx, ref.in_idx) and torch.equal(ours.out_idx, ref.out_idx)
                and ours.bounds == ref.bounds)
        if not same:
            raise SystemExit(f"{count} voxels: submanifold_map differs from the plain search")
        plain = median_ms(lambda: plain_map(coords), args.repeats)
        fast = median_ms(lambda: submanifold_map(coords, SHAPE), args.repeats)
        out.append({"voxels": len(coords), "pairs": len(ours.in_idx), "plain_ms": plain,
                    "submanifold_map_ms": fast, "speedup": round(plain / fast, 2), "same_pairs": same})
    print(json.dumps(out, indent=1))
    bench_record.write(args.out, [
        {"what": f"submanifold 3^3 kernel map of {r['voxels'] / 1e3:.0f}k voxels of two sweep-like frames on the Pi3DET "
                 "grid, against the plain per-offset search (same pairs in the same order, checked)",
         "median": f"{r['submanifold_map_ms']:.1f} vs {r['plain_ms']:.1f} ms ({r['speedup']:.1f}x)"} for r in out],
        {"maps": out, "threads": 1})


if __name__ == "__main__":
    main()
