"""Resumable mmengine checkpoints that load with ``torch.load(weights_only=True)``.

mmengine pickles its message hub into checkpoints (``HistoryBuffer`` objects,
which carry bound methods, and numpy arrays and scalars), which torch >= 2.6's
safe loader refuses; allow-listing those classes would not be enough, and
allow-listing ``getattr`` would defeat the protection. The hook from
:func:`weights_only_hook` turns them into tagged plain values (tensors, Python
numbers) on save and back on load, so our own checkpoints stay weights-only
loadable and resuming needs no exception. Used by the generator and segmentor
trainers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

_TAG = "__omnilidar_type__"


def to_plain(obj):
    """HistoryBuffers and numpy values -> tagged dicts of tensors / Python numbers."""
    from mmengine.logging import HistoryBuffer

    if isinstance(obj, HistoryBuffer):
        log, count = obj.data
        return {_TAG: "HistoryBuffer", "log": torch.as_tensor(np.asarray(log, np.float64)),
                "count": torch.as_tensor(np.asarray(count, np.float64)), "max_length": int(obj.max_length)}
    if isinstance(obj, np.ndarray):
        if obj.dtype == object:
            raise TypeError("object arrays cannot go into a weights-only checkpoint")
        return {_TAG: "ndarray", "data": torch.from_numpy(np.ascontiguousarray(obj).copy())}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        return {k: to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(to_plain(v) for v in obj)
    return obj


def from_plain(obj):
    """Inverse of :func:`to_plain`."""
    from mmengine.logging import HistoryBuffer

    if isinstance(obj, dict):
        tag = obj.get(_TAG)
        if tag == "HistoryBuffer":
            return HistoryBuffer(obj["log"].tolist(), obj["count"].tolist(), obj["max_length"])
        if tag == "ndarray":
            return obj["data"].numpy()
        return {k: from_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(from_plain(v) for v in obj)
    return obj


def weights_only_hook(meta: dict):
    """An mmengine hook making resumable checkpoints safe-loadable; ``meta`` is stored in them."""
    from mmengine.hooks import Hook

    class WeightsOnlyCheckpointHook(Hook):
        priority = "VERY_LOW"

        def before_save_checkpoint(self, runner, checkpoint: dict) -> None:
            for key in ("message_hub", "meta"):
                if key in checkpoint:
                    checkpoint[key] = to_plain(checkpoint[key])
            checkpoint.setdefault("meta", {})["omnilidar"] = to_plain(meta)

        def after_load_checkpoint(self, runner, checkpoint: dict) -> None:
            for key in ("message_hub", "meta"):
                if key in checkpoint:
                    checkpoint[key] = from_plain(checkpoint[key])

    return WeightsOnlyCheckpointHook()


def last_checkpoint(work_dir: Path) -> Path | None:
    """The checkpoint mmengine marked as last in ``work_dir`` (None if none exists)."""
    marker = Path(work_dir) / "last_checkpoint"
    if not marker.exists():
        return None
    path = Path(marker.read_text().strip())
    return path if path.exists() else None


def checkpoint_iteration(path: Path) -> int:
    """The iteration a resumable checkpoint was saved at."""
    return int(torch.load(path, map_location="cpu", weights_only=True, mmap=True)["meta"]["iter"])


def iteration_hooks(log_interval: int, checkpoint_interval: int, keep_checkpoints: int) -> dict:
    """mmengine ``default_hooks`` of our iteration-based trainers: timing, logging with
    ETA, LR schedule, and resumable checkpoints every ``checkpoint_interval`` steps."""
    return dict(
        timer=dict(type="IterTimerHook"),
        logger=dict(type="LoggerHook", interval=log_interval, log_metric_by_epoch=False),
        param_scheduler=dict(type="ParamSchedulerHook"),
        checkpoint=dict(type="CheckpointHook", interval=checkpoint_interval, by_epoch=False,
                        max_keep_ckpts=keep_checkpoints, save_last=True),
        sampler_seed=None,
    )


def resumable_runner_args(resume_from: Path | None, seed: int, log_interval: int) -> dict:
    """The mmengine ``Runner`` arguments our iteration-based trainers share: seeded,
    resumed from ``resume_from`` (see :func:`last_checkpoint`) when there is one, logging
    per iteration in the mmengine scope."""
    return dict(
        randomness=dict(seed=int(seed)),
        resume=resume_from is not None,
        load_from=str(resume_from) if resume_from else None,
        log_processor=dict(by_epoch=False, window_size=log_interval),
        log_level="INFO",
        default_scope="mmengine",
    )
