"""Training a segmentor (MinkUNet or SPVCNN) from scratch with mmengine's Runner.

The Runner provides the iteration loop, SGD (momentum 0.9, Nesterov, weight
decay) through an optimizer wrapper (``AmpOptimWrapper`` with fp16 autocast on
CUDA), a linear warm-up followed by cosine annealing to zero, resumable
checkpoints in an undeclared work directory, and log lines with loss, learning
rate, time per step and ETA.

Data come from :class:`~omnilidar.downstream.seg.dataset.MixedBatchSampler`
(an endless deterministic stream over real and generated scans), so the
schedule is counted in iterations: ``schedule.iterations`` when set, else
``epochs`` passes over the mixed training set. The model weights are drawn from
a torch generator seeded from the run's seed, augmentation from per-draw numpy
generators (see :mod:`.dataset`): the same config and seed give the same
training trajectory on the same device.

The work directory is keyed by a hash of everything that determines the
trajectory (settings, backbone, scan lists, seed); an interrupted run resumes
from its last checkpoint, a changed one starts afresh.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from omnilidar.checkpoints import (checkpoint_iteration, iteration_hooks, last_checkpoint, resumable_runner_args,
                                   weights_only_hook)
from omnilidar.downstream.seg.checkpoints import save_payload
from omnilidar.downstream.seg.dataset import MixedBatchSampler, SegCollate, SegScanDataset, epoch_length
from omnilidar.downstream.seg.label_spaces import LabelSpace
from omnilidar.downstream.seg.models import build_segmentor, model_spec
from omnilidar.downstream.seg.voxelize import IGNORE_INDEX, SegBatch
from omnilidar.errors import InputError

# Keys that do not change what one step computes: changing them resumes the same run.
_RESUMABLE = ("log_interval", "checkpoint_interval", "num_workers")


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(None, f"device {name}: CUDA is not available")
    return torch.device(name)


def total_iterations(schedule: dict, num_real: int, num_generated: int, mixing: dict) -> int:
    """Iterations of a run: ``schedule.iterations`` or ``epochs`` over the mixed set."""
    if schedule.get("iterations"):
        return int(schedule["iterations"])
    per_epoch = math.ceil(epoch_length(num_real, num_generated, mixing) / schedule["batch_size"])
    return int(schedule["epochs"]) * max(1, per_epoch)


def run_hash(settings: dict, backbone: str, real: list[dict], generated: list[dict], seed: int) -> str:
    """Hash of what determines the training trajectory (names the work directory)."""
    relevant = json.loads(json.dumps(settings))
    relevant["schedule"] = {k: v for k, v in settings["schedule"].items() if k not in _RESUMABLE}
    blob = json.dumps({"settings": relevant, "backbone": backbone, "real": real, "generated": generated,
                       "seed": int(seed)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def make_model(net: torch.nn.Module, loss_on: str):
    """Wrap a backbone into an mmengine model whose ``loss`` mode is cross-entropy.

    MinkUNet is supervised on voxels (majority label of each voxel's points,
    mmdet3d's convention); SPVCNN on points (its classifier runs on points).
    """
    from mmengine.model import BaseModel

    class SegmentorModel(BaseModel):
        def __init__(self):
            super().__init__()
            self.net = net

        def forward(self, batch: SegBatch | None = None, mode: str = "loss"):
            if mode != "loss":
                raise ValueError(f"SegmentorModel supports mode='loss' only, got {mode!r}")
            device = next(self.net.parameters()).device
            batch = batch.to(device)
            if loss_on == "voxel":
                logits, target = self.net.voxel_logits(batch), batch.voxel_targets
            else:
                logits, target = self.net(batch), batch.point_targets
            valid = target != IGNORE_INDEX
            if not bool(valid.any()):  # a batch with no labelled point teaches nothing
                return {"loss": logits.float().sum() * 0.0}
            loss = torch.nn.functional.cross_entropy(logits.float(), target, ignore_index=IGNORE_INDEX)
            if not torch.isfinite(loss):
                raise FloatingPointError("training diverged (non-finite loss); lower schedule.lr")
            return {"loss": loss}

    return SegmentorModel()




def train_segmentor(
    settings: dict,
    backbone: str,
    real: list[dict],
    generated: list[dict],
    space: LabelSpace,
    out: str | Path,
    work_dir: str | Path,
    seed: int = 0,
    info: dict | None = None,
) -> dict:
    """Train one segmentor from scratch and write its weights-only payload to ``out``.

    ``settings``: a training section (``models``, ``voxel_size``, ``max_voxels``, ``max_points``,
    ``schedule``, ``augmentation``, ``mixing``, ``backend``, ``device``).
    ``real`` / ``generated``: scan records (:mod:`.dataset`). ``info`` is stored in
    the payload (e.g. which subset and domains). Returns a summary dict.
    """
    from mmengine.runner import Runner

    started = time.time()
    if not real and not generated:
        raise InputError(None, "no training scans")
    sched = settings["schedule"]
    mixing = settings.get("mixing", {"mode": "concat", "generated_share": 0.5})
    device = resolve_device(settings["device"])
    spec = model_spec(backbone, settings["models"][backbone], space.num_classes)
    iterations = total_iterations(sched, len(real), len(generated), mixing)

    run_dir = Path(work_dir) / run_hash(settings, backbone, real, generated, seed)
    run_dir.mkdir(parents=True, exist_ok=True)
    resume_from = last_checkpoint(run_dir)
    skip = checkpoint_iteration(resume_from) if resume_from else 0

    dataset = SegScanDataset(real + generated, space, settings["augmentation"], seed, settings.get("max_points"))
    sampler = MixedBatchSampler(len(real), len(generated), mixing, sched["batch_size"], seed, skip=skip)
    collate = SegCollate(space.num_ids, settings["voxel_size"], settings["max_voxels"], seed)
    loader = torch.utils.data.DataLoader(
        dataset, batch_sampler=sampler, collate_fn=collate,
        num_workers=sched["num_workers"], persistent_workers=sched["num_workers"] > 0,
    )

    gen = torch.Generator().manual_seed(int(np.random.default_rng([int(seed), 0x1417]).integers(2**62)))
    net = build_segmentor(spec, settings["backend"], device, generator=gen)
    model = make_model(net, "voxel" if backbone == "minkunet" else "point")

    optimizer = dict(type="SGD", lr=sched["lr"], momentum=sched["momentum"], nesterov=sched["nesterov"],
                     weight_decay=sched["weight_decay"])
    optim_wrapper = dict(type="OptimWrapper", optimizer=optimizer)
    if device.type == "cuda" and sched["amp"]:
        optim_wrapper = dict(type="AmpOptimWrapper", dtype="float16", optimizer=optimizer)
    warmup = min(int(sched["warmup_iters"]), max(iterations - 1, 0))
    param_scheduler = [dict(type="CosineAnnealingLR", by_epoch=False, begin=warmup, end=iterations,
                            T_max=iterations - warmup, eta_min=0.0)]
    if warmup > 0:
        param_scheduler.insert(0, dict(type="LinearLR", by_epoch=False, start_factor=sched["warmup_start_factor"],
                                       begin=0, end=warmup))

    meta = {"model": spec, "label_space": space.name, "seed": int(seed)}
    runner = Runner(
        model=model,
        work_dir=str(run_dir),
        train_dataloader=loader,
        train_cfg=dict(by_epoch=False, max_iters=iterations, val_interval=iterations + 1),
        optim_wrapper=optim_wrapper,
        param_scheduler=param_scheduler,
        default_hooks=iteration_hooks(sched["log_interval"], sched["checkpoint_interval"], keep_checkpoints=1),
        custom_hooks=[weights_only_hook(meta)],
        launcher="none",
        env_cfg=dict(cudnn_benchmark=False),
        **resumable_runner_args(resume_from, seed, sched["log_interval"]),
    )
    params = sum(p.numel() for p in net.parameters())
    runner.logger.info(
        f"omnilidar segmentor: {backbone} {spec['width']} depth {spec['depth']} ({params / 1e6:.2f} M parameters, "
        f"backend {net.backend}, {device}), {len(real)} real + {len(generated)} generated scans "
        f"(mixing {mixing['mode']}), {iterations} iterations of batch {sched['batch_size']}"
        + (f", resuming at iteration {skip}" if resume_from else "")
    )
    runner.train()

    state = {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}
    bad = [k for k, v in state.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise FloatingPointError(f"non-finite weights after training ({bad[0]}); lower schedule.lr")
    summary = {"iterations": int(runner.iter), "parameters": int(params), "num_real": len(real),
               "num_generated": len(generated), "mixing": mixing, "backend": net.backend,
               "device": str(device), "seconds": round(time.time() - started, 1), "work_dir": str(run_dir)}
    save_payload({
        "state_dict": state, "model": spec, "label_space": space.name,
        "voxel_size": float(settings["voxel_size"]), "config": settings, "seed": int(seed),
        "iterations": summary["iterations"],
        "train": {k: v for k, v in summary.items() if k != "work_dir"} | {"info": info or {}},
    }, out)
    runner.logger.info(f"wrote {out}")
    return summary


def set_threads(threads: int | None) -> None:
    """CPU threads for torch (1 avoids OpenMP spin-waiting when jobs share cores)."""
    if threads:
        torch.set_num_threads(int(threads))
