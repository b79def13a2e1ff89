"""Voxel R-CNN forward/backward timing and CPU-vs-device agreement.

    python benchmarks/bench_det_voxelrcnn.py [--device cuda] [--points 20000] [--config paper|small]

Builds MODEL (paper) or MODEL + CPU_SMALL (small) from config/detectors/voxel_rcnn.yaml on OpenPCDet's
KITTI grid (range [0, -40, -3, 70.4, 40, 1], voxel [0.05, 0.05, 0.1]) with a
synthetic scene (uniform ground clutter plus points inside 10 car boxes), then
times one training step and one inference pass; prints JSON.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import time
from pathlib import Path

import torch
import yaml

import bench_record
from omnilidar.dicts import deep_merge
from omnilidar.downstream.det.models.detector import build_detector

RANGE = [0.0, -40.0, -3.0, 70.4, 40.0, 1.0]
VOXEL = [0.05, 0.05, 0.1]


def synthetic_batch(num_points: int, batch_size: int, seed: int, max_points: int = 5) -> dict:
    g = torch.Generator().manual_seed(seed)
    rows, gts = [], []
    for b in range(batch_size):
        centres = torch.rand(10, 2, generator=g) * torch.tensor([60.0, 70.0]) + torch.tensor([5.0, -35.0])
        boxes = torch.cat([centres, torch.full((10, 1), -0.9), torch.tensor([[3.9, 1.6, 1.56]]).expand(10, 3),
                           torch.rand(10, 1, generator=g) * math.pi, torch.ones(10, 1)], 1)
        n_box = num_points // 40
        pts = [torch.rand(num_points - 10 * n_box, 3, generator=g) * torch.tensor([70.4, 80.0, 0.3])
               + torch.tensor([0.0, -40.0, -1.7])]
        for box in boxes:
            local = (torch.rand(n_box, 3, generator=g) - 0.5) * box[3:6]
            c, s = math.cos(float(box[6])), math.sin(float(box[6]))
            pts.append(torch.stack([local[:, 0] * c - local[:, 1] * s + box[0],
                                    local[:, 0] * s + local[:, 1] * c + box[1], local[:, 2] + box[2]], 1))
        xyz = torch.cat(pts)
        rows.append(torch.cat([torch.full((len(xyz), 1), float(b)), xyz, torch.rand(len(xyz), 1, generator=g)], 1))
        gts.append(boxes)
    points = torch.cat(rows)
    grid = torch.tensor([round((RANGE[i + 3] - RANGE[i]) / VOXEL[i]) for i in range(3)])
    cell = ((points[:, 1:4] - torch.tensor(RANGE[:3])) / torch.tensor(VOXEL)).floor().long()
    inside = ((cell >= 0) & (cell < grid)).all(1)
    points, cell = points[inside], cell[inside]
    coords = torch.cat([points[:, :1].long(), cell[:, [2, 1, 0]]], 1)
    uniq, inverse = torch.unique(coords, dim=0, return_inverse=True)
    order = torch.argsort(inverse, stable=True)
    inv_sorted = inverse[order]
    first = torch.searchsorted(inv_sorted, torch.arange(len(uniq)))
    slot = torch.arange(len(order)) - first[inv_sorted]
    keep = slot < max_points
    voxels = torch.zeros(len(uniq), max_points, 4)
    voxels[inv_sorted[keep], slot[keep]] = points[order[keep], 1:]
    counts = torch.bincount(inverse, minlength=len(uniq)).clamp(max=max_points)
    return {"batch_size": batch_size, "points": points, "voxels": voxels, "voxel_num_points": counts,
            "voxel_coords": uniq.int(), "gt_boxes": torch.stack(gts)}


def to_device(batch: dict, device) -> dict:
    return {k: v.to(device) if torch.is_tensor(v) else v for k, v in batch.items()}


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--points", type=int, default=20000)
    parser.add_argument("--batch-size", type=int, default=2)
    parser.add_argument("--config", default="paper", choices=["paper", "small"])
    parser.add_argument("--repeats", type=int, default=3)
    bench_record.out_arg(parser)
    args = parser.parse_args()
    device = torch.device(args.device)
    doc = yaml.safe_load((Path(__file__).parent.parent / "config" / "detectors" / "voxel_rcnn.yaml").read_text())
    cfg = deep_merge(doc["MODEL"], doc["CPU_SMALL"]) if args.config == "small" else doc["MODEL"]
    torch.manual_seed(0)
    model = build_detector(copy.deepcopy(cfg), 1, ["Car"], RANGE, VOXEL).to(device)
    batch = synthetic_batch(args.points, args.batch_size, seed=0)
    out = {"device": str(device), "config": args.config, "voxels": len(batch["voxels"])}
    train_s, eval_s = [], []
    for _ in range(args.repeats):
        model.train()
        model.zero_grad()
        sync(device)
        t = time.perf_counter()
        ret, tb, _ = model(to_device(batch, device))
        ret["loss"].backward()
        sync(device)
        train_s.append(time.perf_counter() - t)
        model.eval()
        t = time.perf_counter()
        with torch.no_grad():
            preds, recall = model(to_device(batch, device))
        sync(device)
        eval_s.append(time.perf_counter() - t)
    out.update(train_step_s=train_s, eval_s=eval_s, loss=ret["loss"].item(), tb=tb, recall=recall,
               num_preds=[len(p["pred_scores"]) for p in preds])
    if device.type == "cuda":
        out["max_memory_gib"] = torch.cuda.max_memory_allocated() / 2 ** 30
    print(json.dumps(out, indent=1))
    bench_record.write(args.out, [{
        "what": f"Voxel R-CNN {'CPU_SMALL' if args.config == 'small' else 'paper MODEL'}, KITTI grid, batch "
                f"{args.batch_size} ({out['voxels'] / 1e3:.0f}k voxels), {device}: training step (forward + backward) / inference",
        "median": f"{sorted(train_s)[len(train_s) // 2]:.2f} / {sorted(eval_s)[len(eval_s) // 2]:.2f} s "
                  f"({torch.get_num_threads()} threads)"}],
        {k: v for k, v in out.items() if k in ("device", "config", "voxels", "train_step_s", "eval_s")})


if __name__ == "__main__":
    main()
