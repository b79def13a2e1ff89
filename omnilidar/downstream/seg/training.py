"""Training a segmentor (MinkUNet or SPVCNN) from scratch with mmengine's Runner.

The Runner provides the iteration loop, SGD (momentum 0.9, Nesterov, weight
decay) through an optimizer wrapper (``AmpOptimWrapper`` with bf16 autocast on
CUDA, fp16 on GPUs without bf16), a linear warm-up followed by cosine annealing to zero, resumable
checkpoints in an undeclared work directory, and log lines with loss, learning
rate, time per step and ETA.

Data come from :class:`~omnilidar.downstream.seg.dataset.MixedBatchSampler`
(an endless deterministic stream over real and generated scans), so the
schedule is counted in iterations: ``schedule.iterations`` when set, else
``epochs`` passes over the mixed training set. The model weights are drawn from
a torch generator seeded from the run's seed, augmentation from per-draw numpy
generators (see :mod:`.dataset`): the same config and seed give the same
training trajectory on the same device.

Each checkpoint stores the job's provenance: everything that determines the
trajectory (settings without the keys that only extend a run, backbone, scan
lists, seed), the code hash of the command, and content digests of its inputs.
A checkpoint in the work directory is resumed only when it matches; otherwise the
run starts fresh and the log says why. The learning rate is a function of the
iteration and the run's length (linear warm-up, cosine to zero), so raising
``iterations`` resumes a finished run and continues on the longer schedule.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from omnilidar.checkpoints import (checkpoint_iteration, iteration_runner, job_provenance, relative_marker,
                                   resume_point, segment_until, trained_state, trajectory_settings,
                                   write_segment_record)
from omnilidar.devices import resolve_device
from omnilidar.downstream.seg.checkpoints import save_payload
from omnilidar.downstream.schedule import total_iterations
from omnilidar.downstream.seg.dataset import MixedBatchSampler, SegCollate, SegScanDataset
from omnilidar.downstream.seg.label_spaces import LabelSpace
from omnilidar.downstream.seg.models import build_segmentor, model_spec
from omnilidar.segnets.voxelize import IGNORE_INDEX, SegBatch
from omnilidar.errors import InputError

def trajectory(settings: dict, backbone: str, real: list[dict], generated: list[dict], lasermix: bool = False) -> dict:
    """What determines the training trajectory besides seed, code and input contents."""
    relevant = trajectory_settings(settings)
    scans = [[r.get("points"), r.get("labels")] for r in real + generated]
    out = {"training": relevant, "backbone": backbone, "num_real": len(real), "num_generated": len(generated),
           "scans": hashlib.sha256(json.dumps(scans, default=str).encode()).hexdigest()}
    return out | ({"lasermix": True} if lasermix else {})


def learning_rate(iteration: int, total: int, schedule: dict) -> float:
    """Linear warm-up from ``lr * warmup_start_factor``, then cosine annealing to zero at ``total``."""
    base = float(schedule["lr"])
    warmup = min(int(schedule["warmup_iters"]), max(total - 1, 0))
    if iteration < warmup:
        start = float(schedule["warmup_start_factor"])
        return base * (start + (1.0 - start) * iteration / warmup)
    span = max(total - warmup, 1)
    return base * 0.5 * (1.0 + math.cos(math.pi * min(iteration - warmup, span) / span))


def schedule_hook(total: int, schedule: dict):
    """Sets every parameter group's learning rate from the global iteration before each step."""
    from mmengine.hooks import Hook

    class LearningRateHook(Hook):
        priority = "VERY_HIGH"

        def before_train_iter(self, runner, batch_idx: int, data_batch=None) -> None:
            lr = learning_rate(runner.iter, total, schedule)
            for group in runner.optim_wrapper.optimizer.param_groups:
                group["lr"] = lr

    return LearningRateHook()


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




def amp_dtype() -> str:
    """Autocast dtype of schedule.amp on CUDA: bf16 where the GPU has it. fp16's range overflowed:
    SPVCNN's loss went non-finite early in training in every seed of one decomposition row on an
    H200 (docs/benchmarks.md); bf16 keeps fp32's exponent range and needs no loss scaling."""
    return "bfloat16" if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else "float16"


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
    inputs: dict | None = None,
    command: str = "train-segmentor",
    lasermix: bool = False,
    segment: tuple[int, int] | None = None,
) -> dict:
    """Train one segmentor from scratch and write its weights-only payload to ``out``.

    ``settings``: a training section (``models``, ``voxel_size``, ``max_voxels``, ``max_points``,
    ``schedule``, ``augmentation``, ``mixing``, ``backend``, ``device``).
    ``real`` / ``generated``: scan records (:mod:`.dataset`). ``info`` is stored in
    the payload (e.g. which subset and domains). ``inputs`` (``{name: path or
    [paths]}``) are the files the records come from; their content digests and the
    code hash of ``command`` key the resumable state in ``work_dir``. With ``lasermix`` every
    draw of a ``generated`` record is LaserMix-ed with a real one (:mod:`.lasermix`). With
    ``segment`` (k, n) it trains only the k-th of n parts of the run, leaves its state in
    ``work_dir`` for the next part and writes a segment record to ``out`` instead of weights.
    Returns a summary dict.
    """

    started = time.time()
    if not real and not generated:
        raise InputError(None, "no training scans")
    sched = settings["schedule"]
    mixing = settings.get("mixing", {"mode": "concat", "generated_share": 0.5})
    device = resolve_device(settings["device"], "downstream device")
    spec = model_spec(backbone, settings["models"][backbone], space.num_classes)
    iterations = total_iterations(sched, len(real), len(generated), mixing)
    until = segment_until(segment, iterations)

    run_dir = Path(work_dir)
    provenance = job_provenance(command, trajectory(settings, backbone, real, generated, lasermix), seed, inputs or {})
    resume_from = resume_point(run_dir, provenance, iterations, log=lambda m: print(m, flush=True))
    skip = checkpoint_iteration(resume_from) if resume_from else 0

    dataset = SegScanDataset(real + generated, space, settings["augmentation"], seed, settings.get("max_points"),
                             lasermix_from=len(real) if lasermix else None,
                             min_confidence=mixing.get("min_confidence", 0.0))
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
        optim_wrapper = dict(type="AmpOptimWrapper", dtype=amp_dtype(), optimizer=optimizer)
    meta = {"model": spec, "label_space": space.name, "seed": int(seed), "provenance": provenance}
    runner = iteration_runner(model, run_dir, loader, iterations, optim_wrapper, sched, [schedule_hook(iterations, sched)], meta,
                              resume_from, seed, until=until)
    params = sum(p.numel() for p in net.parameters())
    runner.logger.info(
        f"omnilidar segmentor: {backbone} {spec['width']} depth {spec['depth']} ({params / 1e6:.2f} M parameters, "
        f"backend {net.backend}, {device}), {len(real)} real + {len(generated)} generated scans "
        f"(mixing {mixing['mode']}{', LaserMix' if lasermix else ''}), {iterations} iterations of batch {sched['batch_size']}"
        + (f" (this segment {segment[0]}/{segment[1]} up to {until})" if segment else "")
        + (f", resuming at iteration {skip}" if resume_from else ", from scratch")
    )
    runner.train()  # loads the resumed state even when there is no step left to take
    relative_marker(run_dir)

    summary = {"iterations": int(runner.iter), "parameters": int(params), "num_real": len(real),
               "num_generated": len(generated), "mixing": mixing, "lasermix": bool(lasermix), "backend": net.backend,
               "device": str(device), "seconds": round(time.time() - started, 1), "work_dir": str(run_dir),
               "resumed_from": skip}
    if segment:
        write_segment_record(out, segment, until, provenance, summary)
        runner.logger.info(f"segment {segment[0]}/{segment[1]} up to iteration {until} done; state in {run_dir}")
        return summary
    state = trained_state(net)
    save_payload({
        "state_dict": state, "model": spec, "label_space": space.name,
        "voxel_size": float(settings["voxel_size"]), "config": settings, "seed": int(seed),
        "iterations": summary["iterations"], "provenance": provenance,
        "train": {k: v for k, v in summary.items() if k != "work_dir"} | {"info": info or {}},
    }, out)
    runner.logger.info(f"wrote {out}")
    return summary

