"""Every paper-scale network on CPU at batch 1: parameters, peak memory, seconds per step.

    python benchmarks/bench_paper_scale.py [--config config/paper.yaml] [--models generator minkunet ...]
                                           [--repeats 1] [--threads N] [--scan PATH] [--text-dim D]

Builds each network at the settings of ``--config`` (resolved with the schema
defaults), in a fresh subprocess per network, and runs one sampling step, then
one training step, on a realistic input, so that shape or memory errors at paper
scale show up here before a cluster allocation is spent:

* generator: the denoiser at ``generator.range_image`` (64x1024) with the
  ``generator.model`` architecture; training step = the diffusion objective
  through the trainer's mmengine adapter (``epsilon_loss``), backward, gradient
  clipping, AdamW; sampling step = ``generate`` with the configured sampler and
  one step (one denoiser call). The input is a real scan projected and encoded.
  The paper's text encoder is CLIP, whose weights are not reachable offline: the
  prompt tokens are random, at CLIP's embedding size (768 for
  clip-vit-large-patch14, read from a local model directory when
  ``generator.text.clip_model`` is one) and ``max_tokens`` tokens per prompt.
* minkunet, spvcnn (and the labeler when its architecture differs): the
  ``downstream.models`` widths on the scan voxelised at ``downstream.voxel_size``;
  training step = the trainer's loss (voxel loss for MinkUNet, point loss for
  SPVCNN) with the ``downstream.max_voxels`` cap, backward, SGD with the
  schedule's settings; inference = one forward over every voxel (no cap).
* frd, frid: RangeNet++ DarkNet-53 / DarkNet-21 at the published width 32
  (what official weights bring; the config's self-trained width is smaller);
  fsvd, fpvd, fpd: MinkUNet / SPVCNN / PointNet at ``evaluation.extractors.arch``
  (W16, LiDM's size; PointNet with the pretext's 19 classes, 3 outputs more than
  the official ShapeNet head, which cannot take the pretext loss). Inference = feature
  extraction from the protocol views of the scan at 64x1024; training step = the
  self-training pretext loss, backward, AdamW (FPD with 2 scans: PointNet's
  BatchNorm needs two).
* voxel_rcnn, pv_rcnn: the detectors of ``downstream.det`` (OpenPCDet's published
  MODEL sections in ``config/paper.yaml``) for the Quadruped platform (Car and
  Pedestrian anchors) over Pi3DET's range [0, -75.2, -2, 75.2, 75.2, 4] at its
  voxel size; the scan's points in that range with three hand-placed boxes (two
  cars, a pedestrian: speed does not depend on where); training step = the
  detector's loss (RPN, point head, R-CNN), backward, gradient clipping, Adam
  one-cycle with the schedule's settings, voxels capped at ``max_voxels_train``;
  inference = one forward with post-processing (``max_voxels_test``).

Peak memory is the process's maximum resident set (``ru_maxrss``) after the
sampling step and after the training step; "above base" subtracts the maximum
reached after imports and input preparation, before the network is built. Times
are medians over ``--repeats`` steps, the first included (with the default of 1
it is the cost of one cold step). Mixed precision (bf16 / AMP) is CUDA-only and
off here.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import bench_record  # benchmarks/, the script's folder

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SCAN = ROOT.parent / "shared" / "data" / "real" / "semantickitti" / "sequences" / "00" / "velodyne" / "000000.bin"
# Token-embedding sizes of the CLIP text models the config may name (hidden_size of their text config).
CLIP_TEXT_DIMS = {
    "openai/clip-vit-large-patch14": 768,
    "openai/clip-vit-large-patch14-336": 768,
    "openai/clip-vit-base-patch32": 512,
    "openai/clip-vit-base-patch16": 512,
}
MINILM_DIM = 384
MODELS = ("generator", "minkunet", "spvcnn", "labeler", "frd", "frid", "fsvd", "fpvd", "fpd", "voxel_rcnn", "pv_rcnn")


# --------------------------------------------------------------------------- child side


def _max_rss_mib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def _timed(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _load_scan(path: str | None):
    """(N, 4) float32 x, y, z, remission of a real scan, or a synthetic stand-in of the same size."""
    import numpy as np

    from omnilidar.io.semantickitti import read_points

    if path:
        return read_points(path), str(path)
    if DEFAULT_SCAN.exists():
        return read_points(DEFAULT_SCAN), str(DEFAULT_SCAN.relative_to(ROOT.parent))
    # 64 beams x 1875 azimuths over a ground plane 1.73 m below, walls at 8-40 m
    rng = np.random.default_rng(0)
    elev = np.deg2rad(np.linspace(2.0, -24.8, 64))[:, None]
    azim = np.linspace(-np.pi, np.pi, 1875, endpoint=False)[None, :]
    wall = rng.uniform(8.0, 40.0, (1, 1875)).repeat(64, 0)
    ground = np.where(np.sin(elev) < 0, 1.73 / np.maximum(-np.sin(elev), 1e-3), np.inf)
    r = np.minimum(wall, ground) + rng.normal(0, 0.02, (64, 1875))
    xyz = np.stack([r * np.cos(elev) * np.cos(azim), r * np.cos(elev) * np.sin(azim), r * np.sin(elev)], -1)
    pts = np.concatenate([xyz.reshape(-1, 3), rng.uniform(0, 0.99, (xyz.size // 3, 1))], 1)
    return pts.astype(np.float32), "synthetic 64 x 1875 stand-in"


def _range_image(points, spec):
    from omnilidar.data.range_image import encode, project

    proj = project(points, spec)
    return encode(proj.range_img, proj.intensity_img, spec)


def clip_text_dim(text: dict) -> int:
    """Token-embedding size of the configured text encoder (without loading it)."""
    if text["encoder"] == "minilm":
        return MINILM_DIM
    model = text["clip_model"]
    local = Path(model) / "config.json"
    if local.exists():
        cfg = json.loads(local.read_text())
        return int(cfg.get("text_config", cfg).get("hidden_size"))
    if model in CLIP_TEXT_DIMS:
        return CLIP_TEXT_DIMS[model]
    raise SystemExit(f"unknown CLIP model {model!r}: pass --text-dim")


def bench_generator(cfg: dict, scan, repeats: int, text_dim: int | None) -> dict:
    import torch

    from omnilidar.generator.diffusion import generate
    from omnilidar.generator.training import make_diffusion_model
    from omnilidar.generator.unet import build_denoiser, count_parameters, range_image_spec

    g = cfg["generator"]
    spec = range_image_spec(g)
    dim = text_dim or clip_text_dim(g["text"])
    domains = list(g["prompts"])
    n_prompts = sum(len(p) for p in g["prompts"].values())
    n_tok = int(g["text"]["max_tokens"])
    gen = torch.Generator().manual_seed(0)
    tokens = torch.randn(n_prompts, n_tok, dim, generator=gen)  # stand-in for CLIP token embeddings
    mask = torch.ones(n_prompts, n_tok, dtype=torch.bool)
    image = torch.from_numpy(_range_image(scan, spec))[None]
    base = _max_rss_mib()

    torch.manual_seed(0)
    t0 = time.perf_counter()
    den = build_denoiser(g, dim, len(domains))
    build_s = time.perf_counter() - t0
    s = g["sampling"]
    den.eval()
    sample_s = _timed(lambda: generate(den, 0, tokens[0], mask[0], [0], spec.shape, sampler=s["sampler"], steps=1),
                      repeats)
    rss_sample = _max_rss_mib()

    den.train()
    model = make_diffusion_model(den, g, tokens, mask, seed=0)
    t = g["training"]
    opt = torch.optim.AdamW(model.parameters(), lr=t["lr"], betas=tuple(t["betas"]), weight_decay=t["weight_decay"])
    batch = {"image": image, "domain": torch.zeros(1, dtype=torch.long), "prompt": torch.zeros(1, dtype=torch.long)}

    def train_step():
        model.iteration += 1
        loss = model(**batch)["loss"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), t["grad_clip"])
        opt.step()

    train_s = _timed(train_step, repeats)
    return {"parameters": count_parameters(den), "build_s": build_s, "train_s": train_s, "sample_s": sample_s,
            "rss_base": base, "rss_sample": rss_sample, "rss_train": _max_rss_mib(),
            "input": f"{spec.height}x{spec.width} image, {n_tok} x {dim}-d random prompt tokens",
            "note": f"{s['sampler']} x {s['steps']} steps ~ {sample_s * s['steps']:.0f} s per scan"}


def _segmentor_rows(cfg: dict) -> dict[str, tuple[str, dict, float, int | None, dict]]:
    """name -> (backbone, model settings, voxel size, max voxels, schedule)."""
    d = cfg["downstream"]
    rows = {b: (b, d["models"][b], d["voxel_size"], d["max_voxels"], d["schedule"]) for b in ("minkunet", "spvcnn")}
    lab = d["labeler"]
    rows["labeler"] = (lab["backbone"], lab["model"], lab["voxel_size"], lab["max_voxels"], lab["schedule"])
    return rows


def labeler_is_duplicate(cfg: dict) -> bool:
    rows = _segmentor_rows(cfg)
    backbone, model, voxel, cap, _ = rows["labeler"]
    b2, m2, v2, c2, _ = rows[backbone]
    return (model["width"], model["depth"], voxel, cap) == (m2["width"], m2["depth"], v2, c2)


def bench_segmentor(name: str, cfg: dict, scan, repeats: int) -> dict:
    import numpy as np
    import torch

    from omnilidar.downstream.seg.dataset import SegCollate
    from omnilidar.downstream.seg.models import build_segmentor, model_spec
    from omnilidar.downstream.seg.training import make_model

    backbone, settings, voxel, cap, sched = _segmentor_rows(cfg)[name]
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 20, len(scan)).astype(np.uint8)  # random train ids: speed does not depend on them
    item = {"points": scan, "labels": labels, "path": None}
    train_batch = SegCollate(20, voxel, cap, 0)([{**item, "draw": 0}])["batch"]  # capped, as in training
    full_batch = SegCollate(20, voxel)([{**item, "draw": None}])["batch"]  # every voxel, as in evaluation
    base = _max_rss_mib()

    t0 = time.perf_counter()
    spec = model_spec(backbone, settings, 19)
    net = build_segmentor(spec, "torch", "cpu", generator=torch.Generator().manual_seed(0))
    build_s = time.perf_counter() - t0
    net.eval()
    with torch.no_grad():
        sample_s = _timed(lambda: net(full_batch), repeats)
    rss_sample = _max_rss_mib()

    net.train()
    model = make_model(net, "voxel" if backbone == "minkunet" else "point")
    opt = torch.optim.SGD(net.parameters(), lr=sched["lr"], momentum=sched.get("momentum", 0.9),
                          nesterov=sched.get("nesterov", True), weight_decay=sched.get("weight_decay", 1e-4))

    def train_step():
        loss = model(train_batch)["loss"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    train_s = _timed(train_step, repeats)
    nv_full, nv_train = len(full_batch.voxel_coords), len(train_batch.voxel_coords)
    return {"parameters": sum(p.numel() for p in net.parameters()), "build_s": build_s, "train_s": train_s,
            "sample_s": sample_s, "rss_base": base, "rss_sample": rss_sample, "rss_train": _max_rss_mib(),
            "input": f"{len(scan)} points at {voxel} m: {nv_full} voxels (training cap {cap}: {nv_train})",
            "note": f"{backbone} {settings['width']} depth {settings['depth']}"}


def extractor_arch(kind: str, cfg: dict) -> dict:
    """Published sizes for FRD / FRID, the configured ones for FSVD / FPVD (LiDM's W16)
    and FPD (the self-training pretext's 19 classes; the official ShapeNet head has 16)."""
    from omnilidar.metrics.extractors.weights import PROTOCOL_ARCH

    if kind in ("frd", "frid"):
        return dict(PROTOCOL_ARCH[kind])
    return dict(cfg["evaluation"]["extractors"]["arch"][kind])


def bench_extractor(kind: str, cfg: dict, scan, repeats: int) -> dict:
    import numpy as np
    import torch

    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.extractors.training import _loss
    from omnilidar.metrics.extractors.views import range_views
    from omnilidar.metrics.extractors.weights import build_model, wrap

    spec = range_image_spec(cfg["generator"])
    batch = 2 if kind == "fpd" else 1  # PointNet's BatchNorm trains on two scans at least
    views = range_views(np.stack([_range_image(scan, spec)] * batch), spec)
    labels = np.random.default_rng(0).integers(0, 20, (batch, *spec.shape))
    one_view = range_views(_range_image(scan, spec)[None], spec)
    base = _max_rss_mib()

    arch = extractor_arch(kind, cfg)
    t0 = time.perf_counter()
    net = build_model(kind, arch, generator=torch.Generator().manual_seed(0))
    build_s = time.perf_counter() - t0
    extract = wrap(kind, net)
    dims = []
    sample_s = _timed(lambda: dims.append(extract(one_view).shape[1]), repeats)
    rss_sample = _max_rss_mib()

    net.train()
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3)

    def train_step():
        loss = _loss(kind, net, views, labels)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    train_s = _timed(train_step, repeats)
    return {"parameters": sum(p.numel() for p in net.parameters()), "build_s": build_s, "train_s": train_s,
            "sample_s": sample_s, "rss_base": base, "rss_sample": rss_sample, "rss_train": _max_rss_mib(),
            "input": f"{spec.height}x{spec.width} views, {int(one_view['mask'].sum())} masked pixels"
                     + (" (training: 2 scans)" if batch == 2 else ""),
            "note": f"{arch}, {dims[0]}-d features"}


def bench_detector(name: str, cfg: dict, scan, repeats: int) -> dict:
    import numpy as np
    import torch

    from omnilidar.downstream.det.data_config import platform_config
    from omnilidar.downstream.det.dataset import DetCollate
    from omnilidar.downstream.det.model_config import build, model_config
    from omnilidar.downstream.det.optim import adam_onecycle
    from omnilidar.downstream.det.voxelize import points_to_voxels

    det = cfg["downstream"]["det"]
    platform = platform_config(det, "quadruped")
    pcr = np.asarray(platform.point_cloud_range, np.float32)
    points = scan[np.all((scan[:, :3] >= pcr[:3]) & (scan[:, :3] <= pcr[3:]), axis=1)]
    # [x, y, z, dx, dy, dz, heading, class id]: two cars and a pedestrian in front of the sensor.
    boxes = np.array([[12.0, 3.0, -0.95, 3.9, 1.6, 1.56, 0.1, 1], [25.0, -6.0, -0.95, 4.2, 1.7, 1.5, 1.6, 1],
                      [9.0, -3.0, -0.85, 0.8, 0.6, 1.73, 0.0, 2]], np.float32)

    def batch(cap: int) -> dict:
        voxels, coords, num = points_to_voxels(points, platform.voxel_size, platform.point_cloud_range,
                                               det["voxels"]["max_points_per_voxel"], cap)
        return DetCollate()([{"points": points, "voxels": voxels, "voxel_coords": coords, "voxel_num_points": num,
                              "gt_boxes": boxes, "frame_id": "bench", "index": 0}])

    train_batch, test_batch = batch(det["voxels"]["max_voxels_train"]), batch(det["voxels"]["max_voxels_test"])
    base = _max_rss_mib()
    t0 = time.perf_counter()
    torch.manual_seed(0)
    model = model_config(det, name, platform, ROOT / det["detectors"][name]["config"])
    net = build(model, platform, seed=0)
    build_s = time.perf_counter() - t0
    net.eval()
    with torch.no_grad():
        sample_s = _timed(lambda: net(dict(test_batch)), repeats)
    rss_sample = _max_rss_mib()

    net.train()
    sched = det["schedule"]
    optimizer, schedule = adam_onecycle(net, sched, 100)

    def train_step():
        loss = net(dict(train_batch))[0]["loss"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), float(sched["grad_norm_clip"]))
        optimizer.step()

    train_s = _timed(train_step, repeats)
    return {"parameters": sum(p.numel() for p in net.parameters()), "build_s": build_s, "train_s": train_s,
            "sample_s": sample_s, "rss_base": base, "rss_sample": rss_sample, "rss_train": _max_rss_mib(),
            "input": f"{len(points)} points in range, {len(test_batch['voxel_coords'])} voxels at "
                     f"{platform.voxel_size} m (training cap {det['voxels']['max_voxels_train']}: "
                     f"{len(train_batch['voxel_coords'])})",
            "note": f"{name}, Quadruped classes {'/'.join(platform.class_names)}"}


def child(args) -> dict:
    import torch

    from omnilidar.config import load_config

    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    scan, _ = _load_scan(args.scan)
    if args.child == "generator":
        out = bench_generator(cfg, scan, args.repeats, args.text_dim)
    elif args.child in ("minkunet", "spvcnn", "labeler"):
        out = bench_segmentor(args.child, cfg, scan, args.repeats)
    elif args.child in ("voxel_rcnn", "pv_rcnn"):
        out = bench_detector(args.child, cfg, scan, args.repeats)
    else:
        out = bench_extractor(args.child, cfg, scan, args.repeats)
    return {"model": args.child, "threads": torch.get_num_threads(), **out}


# --------------------------------------------------------------------------- parent side


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(ROOT / "config" / "paper.yaml"))
    ap.add_argument("--models", nargs="*", default=list(MODELS), choices=MODELS)
    ap.add_argument("--repeats", type=int, default=1, help="steps timed per network (median; the first included)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--scan", default=None, help="a KITTI .bin scan (default: the shared SemanticKITTI scan)")
    ap.add_argument("--text-dim", type=int, default=None, help="prompt-embedding size (default: from the config)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    bench_record.out_arg(ap)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args)))
        return

    from omnilidar.config import load_config

    cfg = load_config(args.config)
    _, scan_name = _load_scan(args.scan)
    print(f"config {args.config}; scan {scan_name}; batch 1, CPU, float32")
    models = list(args.models)
    if "labeler" in models and labeler_is_duplicate(cfg):
        models.remove("labeler")
        print(f"labeler: same architecture and voxels as {cfg['downstream']['labeler']['backbone']} (not repeated)")
    header = (f"{'model':<10}{'params':>10}{'train s':>10}{'sample s':>10}{'peak RSS MiB':>14}"
              f"{'above base':>12}   input / notes")
    print(header)
    failed, rows, figures = [], [], {}
    for name in models:
        cmd = [sys.executable, __file__, "--child", name, "--config", args.config, "--repeats", str(args.repeats)]
        for flag, value in (("--threads", args.threads), ("--scan", args.scan), ("--text-dim", args.text_dim)):
            if value is not None:
                cmd += [flag, str(value)]
        out = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
        if out.returncode:
            failed.append(name)
            print(f"{name:<10} FAILED\n{out.stderr[-2000:]}", flush=True)
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        peak = max(r["rss_sample"], r["rss_train"])
        print(f"{name:<10}{r['parameters'] / 1e6:>9.2f}M{r['train_s']:>10.2f}{r['sample_s']:>10.2f}{peak:>14.0f}"
              f"{peak - r['rss_base']:>12.0f}   {r['input']}; {r['note']} (threads {r['threads']}; "
              f"sampling peak {r['rss_sample']:.0f} MiB)", flush=True)
        figures[name] = r
        rows.append({"what": f"{name}: {r['parameters'] / 1e6:.2f} M parameters; {r['input']}",
                     "median": f"training step {r['train_s']:.1f} s, sampling / inference step {r['sample_s']:.1f} s, "
                               f"peak RSS {peak:.0f} MiB ({peak - r['rss_base']:.0f} above base; {r['threads']} threads)"})
    bench_record.write(args.out, rows, figures)
    if failed:
        raise SystemExit(f"failed at paper scale: {', '.join(failed)}")


if __name__ == "__main__":
    main()
