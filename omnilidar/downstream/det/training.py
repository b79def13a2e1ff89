"""Training a detector (Voxel R-CNN or PV-RCNN) from scratch with mmengine's Runner.

Follows :mod:`omnilidar.downstream.seg.training`: an endless deterministic
stream of (draw, frame) keys over real and generated frames
(:class:`~omnilidar.downstream.seg.dataset.MixedBatchSampler`), augmentation
seeded by (seed, draw), model weights from a seeded torch generator, resumable
checkpoints in an undeclared work directory keyed by the job's provenance
(settings without the keys that only extend a run, detector, frame lists,
seed, code hash, input digests), log lines with loss, learning rate, time per
step and ETA. The optimiser is OpenPCDet's ``adam_onecycle`` with gradient-norm
clipping (``GRAD_NORM_CLIP``), both from :mod:`omnilidar.downstream.det.optim`;
its learning rate and momentum are set from the global iteration before every
step, so a resumed run continues on the same curve.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch

from omnilidar.checkpoints import (checkpoint_iteration, iteration_runner, job_provenance, relative_marker,
                                   resume_point, segment_until, trained_state, trajectory_settings,
                                   write_segment_record)
from omnilidar.devices import resolve_device
from omnilidar.downstream.det.checkpoints import save_payload
from omnilidar.downstream.det.data_config import PlatformConfig
from omnilidar.downstream.det.dataset import DetCollate, DetScanDataset, batch_to, count_boxes
from omnilidar.downstream.det.model_config import build
from omnilidar.downstream.schedule import total_iterations
from omnilidar.downstream.seg.dataset import MixedBatchSampler
from omnilidar.errors import InputError

def trajectory(settings: dict, detector: str, model: dict, real: list[dict], generated: list[dict]) -> dict:
    """What determines the training trajectory besides seed, code and input contents."""
    relevant = trajectory_settings(settings)
    frames = [[r["points"], r["boxes"], r["names"]] for r in real + generated]
    return {"training": relevant, "detector": detector, "model": model, "num_real": len(real),
            "num_generated": len(generated),
            "frames": hashlib.sha256(json.dumps(frames, default=str).encode()).hexdigest()}


def make_model(net: torch.nn.Module):
    """Wrap a detector into an mmengine model whose ``loss`` mode is the detector's training loss."""
    from mmengine.model import BaseModel

    class DetectorModel(BaseModel):
        def __init__(self):
            super().__init__()
            self.net = net

        def forward(self, batch: dict | None = None, mode: str = "loss"):
            if mode != "loss":
                raise ValueError(f"DetectorModel supports mode='loss' only, got {mode!r}")
            device = next(self.net.parameters()).device
            ret, tb, _ = self.net(batch_to(batch, device))
            loss = ret["loss"]
            if not torch.isfinite(loss):
                raise FloatingPointError("training diverged (non-finite loss); lower schedule.lr")
            out = {"loss": loss}
            for key in ("loss_rpn", "loss_point", "loss_rcnn"):
                if key in tb:
                    out[f"{key}_log"] = torch.as_tensor(float(tb[key]))
            return out

    return DetectorModel()


def schedule_hook(optimizer_schedule):
    """Sets learning rate and momentum from the global iteration before each step."""
    from mmengine.hooks import Hook

    class OneCycleHook(Hook):
        priority = "VERY_HIGH"

        def before_train_iter(self, runner, batch_idx: int, data_batch=None) -> None:
            optimizer_schedule(runner.iter)

    return OneCycleHook()


def train_detector(settings: dict, detector: str, model_cfg: dict, cfg: PlatformConfig, real: list[dict],
                   generated: list[dict], out: str | Path, work_dir: str | Path, seed: int = 0,
                   info: dict | None = None, inputs: dict | None = None,
                   command: str = "train-detector", segment: tuple[int, int] | None = None) -> dict:
    """Train one detector from scratch and write its weights-only payload to ``out``.

    ``settings``: ``device``, ``voxels``, ``schedule``, ``augmentation``, ``mixing``.
    ``real`` / ``generated``: frame records (:mod:`.dataset`). With ``segment`` (k, n) only the
    k-th of n parts of the run (see :func:`omnilidar.downstream.seg.training.train_segmentor`).
    Returns a summary dict.
    """
    from mmengine.optim import OptimWrapper

    from omnilidar.downstream.det.optim import adam_onecycle

    started = time.time()
    if count_boxes(real + generated, cfg.class_names) == 0:
        raise InputError(None, f"the training frames hold no {'/'.join(cfg.class_names)} box; nothing to train on")
    sched = settings["schedule"]
    mixing = settings.get("mixing", {"mode": "concat", "generated_share": 0.5})
    device = resolve_device(settings["device"], "downstream.det.device")
    iterations = total_iterations(sched, len(real), len(generated), mixing)
    until = segment_until(segment, iterations)

    run_dir = Path(work_dir)
    provenance = job_provenance(command, trajectory(settings, detector, model_cfg, real, generated), seed,
                                inputs or {})
    resume_from = resume_point(run_dir, provenance, iterations, log=lambda m: print(m, flush=True))
    skip = checkpoint_iteration(resume_from) if resume_from else 0

    dataset = DetScanDataset(real + generated, cfg, settings["voxels"], settings["augmentation"], seed)
    sampler = MixedBatchSampler(len(real), len(generated), mixing, sched["batch_size"], seed, skip=skip)
    collate = DetCollate()
    loader = torch.utils.data.DataLoader(
        dataset, batch_sampler=sampler, collate_fn=lambda items: {"batch": collate(items)},
        num_workers=sched["num_workers"], persistent_workers=sched["num_workers"] > 0,
    )

    torch.manual_seed(int(np.random.default_rng([int(seed), 0xDE7C]).integers(2**62)))
    net = build(model_cfg, cfg, seed).to(device)
    model = make_model(net)
    optimizer, step_schedule = adam_onecycle(net, sched, iterations)
    optim_wrapper = OptimWrapper(optimizer=optimizer, clip_grad=dict(max_norm=float(sched["grad_norm_clip"])))
    meta = {"detector": detector, "seed": int(seed), "provenance": provenance}
    runner = iteration_runner(model, run_dir, loader, iterations, optim_wrapper, sched, [schedule_hook(step_schedule)], meta,
                              resume_from, seed, until=until)
    params = sum(p.numel() for p in net.parameters())
    runner.logger.info(
        f"omnilidar detector: {detector} ({params / 1e6:.2f} M parameters, {device}), platform {cfg.name} "
        f"classes {', '.join(cfg.class_names)}, {len(real)} real + {len(generated)} generated frames "
        f"(mixing {mixing['mode']}), {iterations} iterations of batch {sched['batch_size']}"
        + (f" (this segment {segment[0]}/{segment[1]} up to {until})" if segment else "")
        + (f", resuming at iteration {skip}" if resume_from else ", from scratch")
    )
    runner.train()  # loads the resumed state even when there is no step left to take
    relative_marker(run_dir)

    summary = {"iterations": int(runner.iter), "parameters": int(params), "num_real": len(real),
               "num_generated": len(generated), "mixing": mixing, "device": str(device),
               "seconds": round(time.time() - started, 1), "resumed_from": skip}
    if segment:
        write_segment_record(out, segment, until, provenance, summary)
        runner.logger.info(f"segment {segment[0]}/{segment[1]} up to iteration {until} done; state in {run_dir}")
        return summary
    state = trained_state(net)
    save_payload({"model_state": state, "detector": detector, "model_cfg": model_cfg, "data": cfg.as_dict(),
                  "config": settings, "seed": int(seed), "iterations": summary["iterations"],
                  "provenance": provenance, "train": summary | {"info": info or {}}}, out)
    runner.logger.info(f"wrote {out}")
    return summary
