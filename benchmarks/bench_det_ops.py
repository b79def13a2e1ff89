"""Speed of the detection box and point operators (omnilidar.downstream.det.ops).

Synthetic, seeded inputs at the sizes the detectors meet: rotated IoU of N x N
boxes spread over a 140 m x 140 m scene and of proposals crowded around a few
objects, NMS over crowded proposals (PV-RCNN trains with NMS_PRE_MAXSIZE 9000),
points in boxes for a 120k-point scan, FPS of 2048 keypoints and ball queries.

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

from omnilidar.downstream.det.ops import iou, nms, points, sampling


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                        help="auto: CPU, then CUDA when present")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="skip the largest sizes")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    devices = [args.device] if args.device != "auto" else ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for name in devices:
        device = torch.device(name)
        label = torch.cuda.get_device_name(device) if name == "cuda" else f"cpu, {torch.get_num_threads()} threads"
        print(f"# {label}, torch {torch.__version__}")
        gen = torch.Generator().manual_seed(0)
        for title, fn in cases(gen, device, args.quick):
            print(f"{title:55s} {median_ms(fn, device, args.repeats):10.2f} ms", flush=True)


if __name__ == "__main__":
    main()
