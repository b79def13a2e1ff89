"""Speed of the detection box and point operators (omnilidar.downstream.det.ops).

Synthetic, seeded inputs at the sizes the detectors meet: rotated IoU of N x N
boxes spread over a 140 m x 140 m scene and of proposals crowded around a few
objects, NMS over crowded proposals (PV-RCNN trains with NMS_PRE_MAXSIZE 9000),
points in boxes for a 120k-point scan, FPS of 2048 keypoints and ball queries, and
Voxel R-CNN's voxel query for the RoI grid points of a batch (32 RoIs x 4^3 or
6^3 points per frame, two frames, a 9 x 9 x 9 window) against the plain window
scan that looks up every window cell of every centre (same result, checked).

    python benchmarks/bench_det_ops.py                 # CPU, plus CUDA when present
    python benchmarks/bench_det_ops.py --device cpu --threads 1 --quick

Prints one line per case: the median milliseconds over --repeats runs (after
one warm-up run; CUDA timings synchronise before and after each run).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import torch

import bench_record
from omnilidar.downstream.det.ops import nms, sampling
from omnilidar.geometry import points_in_boxes as points, rotated_iou as iou


def scene_boxes(gen: torch.Generator, n: int, half_extent: float = 70.0) -> torch.Tensor:
    """Car-sized boxes spread over the scene."""
    xy = (torch.rand(n, 2, generator=gen) * 2 - 1) * half_extent
    z = torch.rand(n, 1, generator=gen) - 1.0
    size = torch.tensor([3.9, 1.6, 1.56]) * (0.8 + 0.4 * torch.rand(n, 3, generator=gen))
    heading = (torch.rand(n, 1, generator=gen) * 2 - 1) * math.pi
    return torch.cat([xy, z, size, heading], dim=1)


def crowded_boxes(gen: torch.Generator, n: int, objects: int = 30) -> torch.Tensor:
    """Proposals jittered around a few objects, as a detector's head emits them."""
    centres = scene_boxes(gen, objects)
    pick = torch.randint(0, objects, (n,), generator=gen)
    jitter = torch.randn(n, 7, generator=gen) * torch.tensor([0.5, 0.5, 0.2, 0.3, 0.15, 0.1, 0.3])
    return centres[pick] + jitter


def window_scan_voxel_query(max_range, radius, nsample, xyz, new_xyz, new_coords, point_indices):
    """The baseline: every (centre, window cell) pair looked up in the dense map."""
    zr, yr, xr = max_range
    _, nz, ny, nx = point_indices.shape
    dev = new_xyz.device
    grid = torch.meshgrid(*[torch.arange(-r, r + 1, device=dev) for r in (zr, yr, xr)], indexing="ij")
    offsets = torch.stack([g.reshape(-1) for g in grid], 1)
    cell = new_coords[:, None, 1:].long() + offsets[None]
    inside = ((cell >= 0) & (cell < torch.tensor([nz, ny, nx], device=dev))).all(2)
    cell = torch.where(inside[..., None], cell, 0)
    lin = ((new_coords[:, None, 0].long() * nz + cell[..., 0]) * ny + cell[..., 1]) * nx + cell[..., 2]
    neighbour = torch.where(inside, point_indices.reshape(-1).long()[lin], -1)
    d2 = ((xyz[neighbour.clamp(min=0)] - new_xyz[:, None]) ** 2).sum(-1)
    hit = (neighbour >= 0) & (d2 <= radius * radius)
    key = torch.where(hit, torch.arange(len(offsets), device=dev), len(offsets))
    first = torch.topk(key, nsample, dim=1, largest=False).values
    picked = torch.gather(neighbour, 1, first.clamp(max=len(offsets) - 1))
    picked = torch.where(first < len(offsets), picked, picked[:, :1])
    empty = ~hit.any(1)
    return torch.where(empty[:, None], 0, picked), empty


def voxel_query_scene(gen: torch.Generator, grid_size: int):
    """Occupied stride-2 voxels of a 75 m x 150 m scene (ground plus 30 cars) and the RoI
    grid points of 32 proposals per frame near the cars, two frames."""
    voxel, dims = torch.tensor([0.2, 0.2, 0.3]), (21, 752, 376)  # z, y, x cells
    rows, centres = [], []
    for b in range(2):
        cars = scene_boxes(gen, 30, half_extent=35.0) + torch.tensor([37.5, 0, 0, 0, 0, 0, 0])
        ground = torch.rand(20_000, 3, generator=gen) * torch.tensor([75.0, 150.0, 0.3]) + torch.tensor([0, -75.0, 0])
        body = (torch.rand(30, 300, 3, generator=gen) - 0.5) * cars[:, None, 3:6] + cars[:, None, :3] + \
            torch.tensor([0, 0, 2.0])
        pts = torch.cat([ground, body.reshape(-1, 3)])
        cell = (pts / voxel).floor().long().clamp(min=0)
        cell = torch.minimum(cell, torch.tensor(dims[::-1]) - 1)
        rows.append(torch.unique(torch.cat([torch.full((len(cell), 1), b), cell[:, [2, 1, 0]]], 1), dim=0))
        rois = cars[torch.randint(0, 30, (32,), generator=gen)] + torch.randn(32, 7, generator=gen) * 0.3
        g = (torch.arange(grid_size) + 0.5) / grid_size - 0.5
        local = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
        centres.append((local[None] * rois[:, None, 3:6] + rois[:, None, :3] + torch.tensor([0, 0, 2.0])).reshape(-1, 3))
    coords = torch.cat(rows)
    xyz = (coords[:, [3, 2, 1]].float() + 0.5) * voxel
    point_indices = torch.full((2, *dims), -1, dtype=torch.int32)
    point_indices[coords[:, 0], coords[:, 1], coords[:, 2], coords[:, 3]] = torch.arange(len(coords), dtype=torch.int32)
    new_xyz = torch.cat(centres)
    batch = torch.arange(2).repeat_interleave(len(centres[0]))
    new_coords = torch.cat([batch[:, None], (new_xyz / voxel).floor().long()[:, [2, 1, 0]]], 1)
    return xyz, new_xyz, new_coords, point_indices, sampling.VoxelMap.from_coords(coords, point_indices.shape)


def median_ms(fn, device: torch.device, repeats: int) -> float:
    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    fn()
    sync()
    times = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def cases(gen: torch.Generator, device: torch.device, quick: bool):
    sizes = (100, 500) if quick else (100, 500, 2000)
    for n in sizes:
        boxes = scene_boxes(gen, n).to(device)
        yield f"boxes_iou_bev {n} x {n} scene", lambda b=boxes: iou.boxes_iou_bev(b, b)
    for n in sizes:
        boxes = crowded_boxes(gen, n).to(device)
        yield f"boxes_iou_bev {n} x {n} crowded", lambda b=boxes: iou.boxes_iou_bev(b, b)
        yield f"boxes_iou3d {n} x {n} crowded", lambda b=boxes: iou.boxes_iou3d(b, b)
    for n in ((1000, 4096) if quick else (1000, 4096, 9000)):
        boxes = crowded_boxes(gen, n, objects=max(30, n // 100)).to(device)
        scores = torch.rand(n, generator=gen).to(device)
        yield f"nms_rotated {n} crowded, thresh 0.7, post 512", \
            lambda b=boxes, s=scores: nms.nms_rotated(b, s, 0.7, post_max_size=512)
    scan = torch.cat([(torch.rand(120_000, 2, generator=gen) * 2 - 1) * 70,
                      torch.rand(120_000, 1, generator=gen) * 3 - 2], dim=1).to(device)
    boxes = scene_boxes(gen, 50).to(device)
    yield "points_in_boxes 120k points x 50 boxes", lambda: points.points_in_boxes(scan, boxes)
    raw = scan[:16_384][None].contiguous()
    yield "farthest_point_sample 16384 -> 2048", lambda: sampling.farthest_point_sample(raw, 2048)
    keypoints = raw[0, sampling.farthest_point_sample(raw, 2048)[0]]
    counts = torch.tensor([16_384], device=device)
    yield "ball_query r=1.6 ns=16, 2048 centres x 16384 points", \
        lambda: sampling.ball_query(1.6, 16, raw[0], counts, keypoints, torch.tensor([2048], device=device))
    for grid_size in (4, 6):
        xyz, new_xyz, new_coords, dense, voxel_map = (t.to(device) if torch.is_tensor(t) else t
                                                      for t in voxel_query_scene(gen, grid_size))
        args = ((4, 4, 4), 0.4, 16, xyz, new_xyz, new_coords)
        want = window_scan_voxel_query(*args, dense)
        got = sampling.voxel_query(*args, voxel_map)
        if not (torch.equal(want[0], got[0]) and torch.equal(want[1], got[1])):
            raise AssertionError("voxel_query and the window scan disagree")
        title = f"voxel_query r=0.4 ns=16, {len(new_xyz)} centres, 9^3 window"
        yield f"{title} (window scan)", lambda a=args, d=dense: window_scan_voxel_query(*a, d)
        yield f"{title} (ours, sparse map)", lambda a=args, m=voxel_map: sampling.voxel_query(*a, m)
        yield f"{title} (ours, dense map)", lambda a=args, d=dense: sampling.voxel_query(*a, d)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                        help="auto: CPU, then CUDA when present")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="skip the largest sizes")
    bench_record.out_arg(parser)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    devices = [args.device] if args.device != "auto" else ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    rows, figures = [], {}
    for name in devices:
        device = torch.device(name)
        threads = torch.get_num_threads()
        label = torch.cuda.get_device_name(device) if name == "cuda" else f"cpu, {threads} thread{'s' * (threads > 1)}"
        print(f"# {label}, torch {torch.__version__}")
        gen = torch.Generator().manual_seed(0)
        for title, fn in cases(gen, device, args.quick):
            ms = median_ms(fn, device, args.repeats)
            print(f"{title:75s} {ms:10.2f} ms", flush=True)
            figures.setdefault(label, {})[title] = ms
            rows.append({"what": f"{title} ({label})", "median": f"{ms:.3g} ms"})
    bench_record.write(args.out, rows, figures)


if __name__ == "__main__":
    main()
