"""Time PV-RCNN's own stages at paper scale on one synthetic frame.

Stages (OpenPCDet's pv_rcnn.yaml settings from config/detectors/pv_rcnn.yaml):
voxel set abstraction (2048 FPS keypoints, SA on raw points and x_conv1..4, BEV
interpolation), the keypoint head, and RoI-grid pooling of 128 RoIs per frame
(6x6x6 grid, two radii), forward and forward+backward, median of repeats.
The sparse maps are the frame's occupied voxels at strides 1, 2, 4, 8 with
random features (the backbone itself is not timed here).

With ``--whole paper|small`` it instead times the whole detector (one training
step and one inference pass on two frames, Car only) on the synthetic scene of
bench_det_voxelrcnn.py, for comparison with Voxel R-CNN's numbers there.

    python benchmarks/bench_det_pvrcnn.py [--points 20000] [--device cpu|cuda] [--repeats 3]
    python benchmarks/bench_det_pvrcnn.py --whole small [--points 20000] [--device cpu|cuda]
"""

from __future__ import annotations

import argparse
import copy
import importlib.util
import json
import statistics
import time
from pathlib import Path

import torch
import yaml

import bench_record
from omnilidar.dicts import deep_merge
from omnilidar.downstream.det.models.detector import build_detector
from omnilidar.downstream.det.models.point_head_simple import PointHeadSimple
from omnilidar.downstream.det.models.pointnet2_stack import batch_counts, build_local_aggregation_module
from omnilidar.downstream.det.models.voxel_rcnn_head import VoxelRCNNHead
from omnilidar.downstream.det.models.voxel_set_abstraction import VoxelSetAbstraction
from omnilidar.sparse.tensor import SparseTensor

ROOT = Path(__file__).resolve().parents[1]
POINT_CLOUD_RANGE = [0.0, -40.0, -3.0, 70.4, 40.0, 1.0]  # OpenPCDet KITTI
VOXEL_SIZE = [0.05, 0.05, 0.1]
CHANNELS = {"x_conv1": (16, 1), "x_conv2": (32, 2), "x_conv3": (64, 4), "x_conv4": (64, 8)}


def synthetic_frame(n: int, device, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(POINT_CLOUD_RANGE[:3]), torch.tensor(POINT_CLOUD_RANGE[3:])
    xyz = lo + torch.rand(n, 3, generator=g) * (hi - lo) * 0.999
    points = torch.cat([torch.zeros(n, 1), xyz, torch.rand(n, 1, generator=g)], dim=1)
    grid = ((hi - lo) / torch.tensor(VOXEL_SIZE)).round().long().tolist()
    maps = {}
    for name, (c, stride) in CHANNELS.items():
        v = ((xyz - lo) / (torch.tensor(VOXEL_SIZE) * stride)).floor().int()
        coords = torch.unique(torch.cat([torch.zeros(n, 1, dtype=torch.int32), v], dim=1), dim=0)
        shape = [max(1, -(-s // stride)) for s in grid]
        maps[name] = SparseTensor(torch.randn(coords.shape[0], c, generator=g), coords, shape, 1).to(device)
    bev = torch.randn(1, 256, grid[1] // 8, grid[0] // 8, generator=g)
    rois = torch.cat([lo + torch.rand(128, 3, generator=g) * (hi - lo),
                      torch.tensor([3.9, 1.6, 1.56]).expand(128, 3), torch.rand(128, 1, generator=g) * 3.14], 1)
    gt = torch.cat([rois[:8, :7], torch.ones(8, 1)], dim=1)[None]
    return {"batch_size": 1, "points": points.to(device), "multi_scale_3d_features": maps,
            "spatial_features": bev.to(device), "spatial_features_stride": 8,
            "rois": rois[None].to(device), "gt_boxes": gt.to(device)}


def timed(fn, repeats: int, device) -> float:
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def whole_detector(section: str, points: int, device, repeats: int, out_path) -> None:
    """Train step and inference of the whole PV-RCNN (Car) on bench_det_voxelrcnn's scene."""
    spec = importlib.util.spec_from_file_location("bench_det_voxelrcnn", ROOT / "benchmarks" / "bench_det_voxelrcnn.py")
    voxelrcnn_bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(voxelrcnn_bench)
    doc = yaml.safe_load((ROOT / "config" / "detectors" / "pv_rcnn.yaml").read_text())
    cfg = deep_merge(doc["MODEL"], doc["CPU_SMALL"]) if section == "small" else copy.deepcopy(doc["MODEL"])
    anchors = cfg["DENSE_HEAD"]["ANCHOR_GENERATOR_CONFIG"]
    cfg["DENSE_HEAD"]["ANCHOR_GENERATOR_CONFIG"] = [a for a in anchors if a["class_name"] == "Car"]
    torch.manual_seed(0)
    model = build_detector(cfg, 1, ["Car"], voxelrcnn_bench.RANGE, voxelrcnn_bench.VOXEL).to(device)
    batch = voxelrcnn_bench.to_device(voxelrcnn_bench.synthetic_batch(points, 2, seed=0), device)
    train_s, eval_s = [], []
    for _ in range(repeats):
        model.train()
        model.zero_grad()
        train_s.append(timed(lambda: model(dict(batch))[0]["loss"].backward(), 1, device))
        model.eval()
        with torch.no_grad():
            eval_s.append(timed(lambda: model(dict(batch)), 1, device))
    out = {"device": str(device), "config": section, "points_per_frame": points, "voxels": len(batch["voxels"]),
           "train_step_s": train_s, "eval_s": eval_s, "torch_threads": torch.get_num_threads()}
    if device.type == "cuda":
        out["max_memory_gib"] = torch.cuda.max_memory_allocated() / 2 ** 30
    print(json.dumps(out, indent=1))
    grid = int(cfg["ROI_HEAD"]["ROI_GRID_POOL"]["GRID_SIZE"])
    bench_record.write(out_path, [{
        "what": f"PV-RCNN {'small (CPU_SMALL' if section == 'small' else 'paper (MODEL'}, {grid}^3 RoI grid), two "
                f"{points / 1e3:.0f}k-point frames ({out['voxels'] / 1e3:.0f}k voxels), {device}",
        "median": f"train step {statistics.median(train_s):.2f} s, inference {statistics.median(eval_s):.2f} s "
                  f"({torch.get_num_threads()} threads)"}], out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20000)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--whole", choices=["paper", "small"], help="time the whole detector instead")
    bench_record.out_arg(parser)
    args = parser.parse_args()
    device = torch.device(args.device)
    if args.whole:
        whole_detector(args.whole, args.points, device, args.repeats, args.out)
        return
    torch.manual_seed(0)
    model = yaml.safe_load((ROOT / "config" / "detectors" / "pv_rcnn.yaml").read_text())["MODEL"]
    vsa = VoxelSetAbstraction(model["PFE"], VOXEL_SIZE, POINT_CLOUD_RANGE, num_bev_features=256,
                              num_rawpoint_features=4).to(device).train()
    head = PointHeadSimple(1, vsa.num_point_features_before_fusion, model["POINT_HEAD"]).to(device).train()
    pool_cfg = model["ROI_HEAD"]["ROI_GRID_POOL"]
    pool, _ = build_local_aggregation_module(vsa.num_point_features, pool_cfg)
    pool = pool.to(device).train()
    frame = synthetic_frame(args.points, device)

    def forward():
        batch = head(vsa(dict(frame)))
        feats = batch["point_features"] * batch["point_cls_scores"][:, None]
        grid = VoxelRCNNHead.grid_points_of_rois(batch["rois"][0], int(pool_cfg["GRID_SIZE"])).reshape(-1, 3)
        _, pooled = pool(batch["point_coords"][:, 1:4].contiguous(), batch_counts(batch["point_coords"][:, 0], 1),
                         grid, torch.tensor([grid.shape[0]], dtype=torch.int32, device=device), feats)
        return head.get_loss()[0] + pooled.sum()

    def backward():
        forward().backward()

    forward()  # warm-up
    with torch.no_grad():
        t_fwd = timed(forward, args.repeats, device)
    t_bwd = timed(backward, args.repeats, device)
    print(f"device {device}, {args.points} points, {model['PFE']['NUM_KEYPOINTS']} keypoints, 128 RoIs x "
          f"{int(pool_cfg['GRID_SIZE']) ** 3} grid points, torch threads {torch.get_num_threads()}")
    print(f"VSA + keypoint head + RoI-grid pooling: forward {t_fwd:.3f} s, forward+backward {t_bwd:.3f} s "
          f"(median of {args.repeats})")
    bench_record.write(args.out, [{
        "what": f"PV-RCNN's own stages at paper scale ({args.points / 1e3:.0f}k points, {model['PFE']['NUM_KEYPOINTS']} "
                f"keypoints, 128 RoIs x {int(pool_cfg['GRID_SIZE'])}^3 grid): VSA + keypoint head + RoI-grid pooling",
        "median": f"forward {t_fwd:.2f} s, forward+backward {t_bwd:.2f} s ({torch.get_num_threads()} threads, {device})"}],
        {"forward_s": t_fwd, "forward_backward_s": t_bwd, "points": args.points})


if __name__ == "__main__":
    main()
