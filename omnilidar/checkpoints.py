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

import itertools
import json
from pathlib import Path

import numpy as np
import torch

from omnilidar.errors import InputError
from omnilidar.rerun_reasons import flatten_settings

_TAG = "__omnilidar_type__"
_RUNNER_NUMBERS = itertools.count()
MARKER = "last_checkpoint"  # mmengine's file naming the last checkpoint


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


def weights_only_hooks(meta: dict) -> list:
    """mmengine hooks making resumable checkpoints safe-loadable (``meta``, e.g. the
    run's provenance, is stored in them) and their last-checkpoint marker relative."""
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

    class RelativeMarkerHook(Hook):
        """Runs after mmengine's CheckpointHook: its marker becomes a bare file name."""

        priority = "LOWEST"

        def after_train_iter(self, runner, batch_idx: int, data_batch=None, outputs=None) -> None:
            relative_marker(Path(runner.work_dir))

    return [WeightsOnlyCheckpointHook(), RelativeMarkerHook()]


def last_checkpoint(work_dir: Path) -> Path | None:
    """The checkpoint mmengine marked as last in ``work_dir`` (None if none exists).

    The marker is read as a file name inside ``work_dir`` whatever path mmengine
    wrote into it, so a moved or copied work directory never reads another's state."""
    marker = Path(work_dir) / MARKER
    if not marker.exists():
        return None
    path = Path(work_dir) / Path(marker.read_text().strip()).name
    return path if path.is_file() else None


def relative_marker(work_dir: Path) -> None:
    """Rewrite mmengine's last-checkpoint marker (an absolute path) as a bare file name."""
    marker = Path(work_dir) / MARKER
    if marker.exists():
        name = Path(marker.read_text().strip()).name
        if marker.read_text() != name:
            marker.write_text(name)


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
    resumed from ``resume_from`` (see :func:`resume_point`) when there is one, logging
    per iteration in the mmengine scope.

    Each runner gets its own experiment name: mmengine names its logger and
    visualizer instances after it (by default the second of creation), so two
    runners made within one second would otherwise share, and lose, their logs."""
    import os

    return dict(
        experiment_name=f"omnilidar_{os.getpid()}_{next(_RUNNER_NUMBERS)}",
        randomness=dict(seed=int(seed)),
        resume=resume_from is not None,
        load_from=str(resume_from) if resume_from else None,
        log_processor=dict(by_epoch=False, window_size=log_interval),
        log_level="INFO",
        default_scope="mmengine",
    )


# --------------------------------------------------------------------------- provenance of resumable runs


def job_provenance(command: str, settings: dict, seed: int, inputs: dict) -> dict:
    """What determines a training job's result: the command and the code hash of what
    it runs, its settings (without the keys that only extend a run), its seed, and a
    content digest of each input (``{name: path or [paths]}``; directories count by
    their manifest). Versions are recorded too but do not decide resumption."""
    from omnilidar.manifest import digest
    from omnilidar.provenance import command_code_hash, package_versions

    def digests(paths):
        return [digest(p) for p in paths] if isinstance(paths, (list, tuple)) else digest(paths)

    return {"command": command, "code": command_code_hash(command), "settings": settings, "seed": int(seed),
            "inputs": {name: digests(paths) for name, paths in sorted(inputs.items())},
            "versions": package_versions()}


DECIDING_KEYS = ("command", "code", "settings", "seed", "inputs")  # a provenance's versions do not decide


def provenance_hash(provenance: dict) -> str:
    """A short hash of what decides a training job's result (its provenance without the versions):
    equal for two jobs that provenance_differences finds no difference between."""
    from omnilidar.provenance import config_hash

    return config_hash({k: provenance.get(k) for k in DECIDING_KEYS})


def provenance_differences(stored: dict | None, current: dict) -> list[str]:
    """Why a stored provenance does not match the current one (empty when it does)."""
    if not isinstance(stored, dict):
        return ["no provenance recorded"]
    why = []
    for key in ("command", "code", "seed"):
        if stored.get(key) != current[key]:
            why.append(f"{key} {stored.get(key)} -> {current[key]}")
    old, new = flatten_settings(stored.get("settings", {})), flatten_settings(current["settings"])
    changed = sorted(k for k in old.keys() | new.keys() if old.get(k, "<unset>") != new.get(k, "<unset>"))
    if changed:
        more = f" and {len(changed) - 5} more" if len(changed) > 5 else ""
        why.append("settings changed: " + ", ".join(changed[:5]) + more)
    old_in, new_in = stored.get("inputs", {}), current["inputs"]
    changed = sorted(k for k in old_in.keys() | new_in.keys() if old_in.get(k) != new_in.get(k))
    if changed:
        why.append("input contents changed: " + ", ".join(changed))
    return why


def resume_point(run_dir: Path, provenance: dict, iterations: int, log=print) -> Path | None:
    """The checkpoint in ``run_dir`` to resume, or None to start fresh.

    A checkpoint is resumed only when the provenance it stores matches ``provenance``
    and it is not past ``iterations``; otherwise the directory's state is removed and
    the log says why. Only keys that extend a run (``iterations`` and the like) may
    differ, since callers leave them out of the provenance."""
    import shutil

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt = last_checkpoint(run_dir)
    if ckpt is None:
        log(f"starting fresh in {run_dir}: no checkpoint to resume")
        return None
    meta = torch.load(ckpt, map_location="cpu", weights_only=True, mmap=True).get("meta", {})
    stored = from_plain(meta.get("omnilidar", {})).get("provenance")
    step = int(meta.get("iter", 0))
    why = provenance_differences(stored, provenance)
    if not why and step > iterations:
        why = [f"it is at iteration {step}, past the {iterations} asked for"]
    if why:
        log(f"starting fresh in {run_dir}: its checkpoint {ckpt.name} (iteration {step}) is not this job's: "
            + "; ".join(why))
        shutil.rmtree(run_dir)
        run_dir.mkdir(parents=True)
        return None
    old_versions = stored.get("versions", {})
    moved = {k: (old_versions.get(k), v) for k, v in provenance["versions"].items() if old_versions.get(k) != v}
    if moved:
        log("note: resuming a checkpoint made with other package versions: "
            + ", ".join(f"{k} {a} -> {b}" for k, (a, b) in sorted(moved.items())))
    log(f"resuming at iteration {step} from {ckpt.name} in {run_dir} (provenance matches)")
    return ckpt


def save_tagged_payload(payload: dict, out: str | Path, fmt: str) -> None:
    """Write a final payload (tensors, dicts, lists, strings, numbers) tagged ``format: fmt``, atomically."""
    from omnilidar.io.atomic import atomic_path

    with atomic_path(out) as tmp:
        torch.save({"format": fmt, **payload}, tmp)


def load_weights_only(path: Path, what: str):
    """``torch.load(weights_only=True)`` with one clear error for a missing, corrupt or unsafe file."""
    if not path.is_file():
        raise InputError(path, f"{what} not found")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # corrupt, truncated or unsafe pickles
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise InputError(path, f"not a readable {what} (loaded with weights_only=True): {first}") from None


def load_tagged_payload(path: str | Path, fmt: str, what: str) -> dict:
    """A payload written by :func:`save_tagged_payload` with format ``fmt`` (weights-only)."""
    path = Path(path)
    payload = load_weights_only(path, what)
    if not isinstance(payload, dict) or payload.get("format") != fmt:
        raise InputError(path, f"not an omnilidar {what} ({fmt})")
    return payload


def iteration_runner(model, work_dir: Path, loader, iterations: int, optim_wrapper, schedule: dict,
                     custom_hooks: list, meta: dict, resume_from: Path | None, seed: int, until: int | None = None):
    """An mmengine Runner of a downstream trainer: counted in iterations, one weights-only checkpoint
    kept every ``schedule['checkpoint_interval']``, resuming from ``resume_from`` when given (the
    random streams included, :func:`random_state_hook`). With ``until`` it stops there, leaving its
    checkpoint for the next segment (the learning-rate schedule still spans ``iterations``)."""
    from mmengine.runner import Runner

    stop = until or iterations
    return Runner(
        model=model,
        work_dir=str(work_dir),
        train_dataloader=loader,
        train_cfg=dict(by_epoch=False, max_iters=stop, val_interval=stop + 1),
        optim_wrapper=optim_wrapper,
        default_hooks=iteration_hooks(schedule["log_interval"], schedule["checkpoint_interval"], keep_checkpoints=1),
        custom_hooks=[*custom_hooks, random_state_hook(model), *weights_only_hooks(meta)],
        launcher="none",
        env_cfg=dict(cudnn_benchmark=False),
        **resumable_runner_args(resume_from, seed, schedule["log_interval"]),
    )


def _generator_slots(net: torch.nn.Module):
    """(name, holder, key) of every torch.Generator a module keeps as an attribute, or in a dict
    attribute keyed by device (SeededDropout's, made on first use)."""
    for prefix, module in net.named_modules():
        for attr, value in vars(module).items():
            if isinstance(value, torch.Generator):
                yield f"{prefix}.{attr}", vars(module), attr
            elif isinstance(value, dict) and attr.endswith("generators"):
                for key in value:
                    yield f"{prefix}.{attr}[{key}]", value, key


def random_states(net: torch.nn.Module) -> dict:
    """The random streams a training step draws from: torch's global CPU generator (nn.Dropout)
    and every generator the model keeps (sampling, seeded dropout), as tensors."""
    states = {"torch": torch.get_rng_state()}
    states |= {name: holder[key].get_state() for name, holder, key in _generator_slots(net)}
    return states


def load_random_states(net: torch.nn.Module, states: dict) -> None:
    """Put back what :func:`random_states` saved; generators made on first use are made here."""
    torch.set_rng_state(states["torch"])
    for prefix, module in net.named_modules():
        for attr, value in vars(module).items():
            if isinstance(value, dict) and attr.endswith("generators"):
                head = f"{prefix}.{attr}["
                for name in (n for n in states if n.startswith(head)):
                    key = name[len(head):-1]
                    value.setdefault(key, torch.Generator(device=key))
    for name, holder, key in _generator_slots(net):
        if name in states:
            holder[key].set_state(states[name])


def random_state_hook(model: torch.nn.Module):
    """mmengine hook keeping the random streams in each checkpoint and putting them back before the
    first step after a resume, so that a resumed run (a segment chain) draws what an uninterrupted
    one would: the data loader's iterator, made between loading and that step, draws once more."""
    from mmengine.hooks import Hook

    class RandomStateHook(Hook):
        priority = "VERY_LOW"

        def __init__(self):
            self.pending = None

        def before_save_checkpoint(self, runner, checkpoint: dict) -> None:
            checkpoint["random_states"] = random_states(model)

        def after_load_checkpoint(self, runner, checkpoint: dict) -> None:
            self.pending = checkpoint.get("random_states")

        def before_train_iter(self, runner, batch_idx: int, data_batch=None) -> None:
            if self.pending is not None:
                load_random_states(model, self.pending)
                self.pending = None

    return RandomStateHook()


def segment_until(segment: tuple[int, int] | None, iterations: int) -> int | None:
    """The iteration at which segment k of n of a training of ``iterations`` ends (None: the whole
    training). Segments split the run's own iteration count, which follows the scans the job
    finds, so the chain's length can be fixed before they are counted."""
    if segment is None:
        return None
    k, n = segment
    if not 1 <= k < n:
        raise InputError(None, f"--segment {k}/{n}: a segment is 1..{n - 1} of {n} (the last part is the job itself)")
    return max(1, iterations * k // n)


def parse_segment(text: str) -> tuple[int, int]:
    """``K/N`` -> (K, N) for ``--segment``."""
    try:
        k, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise InputError(None, f"--segment {text!r}: expected K/N, e.g. 1/3") from None
    return k, n


def write_segment_record(out: str | Path, segment: tuple[int, int], until: int, provenance: dict, summary: dict) -> None:
    """A segment job's output: where it stopped, whose state it left (provenance) and how long it took."""
    from omnilidar.io.atomic import atomic_path

    record = {"segment": f"{segment[0]}/{segment[1]}", "segment_until": until, "provenance": provenance,
              **{k: v for k, v in summary.items() if k != "work_dir"}}
    with atomic_path(out) as tmp:
        Path(tmp).write_text(json.dumps(record, indent=1, default=str))


def trained_state(net: torch.nn.Module) -> dict:
    """The trained weights on the CPU; non-finite weights are an error (the run diverged)."""
    state = {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}
    bad = [k for k, v in state.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise FloatingPointError(f"non-finite weights after training ({bad[0]}); lower schedule.lr")
    return state


# Schedule keys that do not change what one step computes or only extend the run: changing them resumes it.
RESUMABLE_SCHEDULE_KEYS = ("log_interval", "checkpoint_interval", "num_workers", "iterations", "epochs")


def trajectory_settings(settings: dict) -> dict:
    """A JSON copy of a trainer's settings without the schedule keys that only extend or log a run."""
    relevant = json.loads(json.dumps(settings))
    relevant["schedule"] = {k: v for k, v in settings["schedule"].items() if k not in RESUMABLE_SCHEDULE_KEYS}
    return relevant
