"""Generator training with mmengine's Runner.

What the Runner provides here: the iteration loop, AdamW through an optimizer
wrapper (gradient clipping; ``AmpOptimWrapper`` with bf16 autocast on CUDA; on a CPU with native
bf16 the loss runs under CPU autocast), a
linear warm-up, EMA of the weights (``EMAHook``), resumable checkpoints in the
work directory, DDP when launched with torchrun (``launcher="pytorch"``) and log
lines with loss, learning rate, time per step and ETA.

Checkpoints stay loadable with ``torch.load(weights_only=True)`` (torch >= 2.6's
default), so resuming needs no exception to the safe loader: mmengine pickles its
message hub (``HistoryBuffer`` objects, whose pickles reference bound methods,
and numpy arrays and scalars), which :func:`omnilidar.checkpoints.weights_only_hook` converts to
plain tensors, dicts and Python numbers in ``before_save_checkpoint`` and back in
``after_load_checkpoint``. Each checkpoint also carries the resolved generator
config (``meta["omnilidar"]["config"]``).

Resuming: each checkpoint stores the job's provenance (settings without the keys
that only extend a run, seed, the code hash of ``train-generator``, and content
digests of the domains index and the prompt cache). A checkpoint in the work
directory is resumed only when that provenance matches; otherwise the run starts
fresh and the log says why (:func:`omnilidar.checkpoints.resume_point`). Raising
``iterations`` resumes. The batch samplers are deterministic streams; on resume the first k
batches are empty (no data is read) while mmengine fast-forwards its loader.
Training noise (t and epsilon) comes from a generator seeded by
(seed, rank, iteration), so a resumed run draws the same noise it would have drawn.
"""

from __future__ import annotations

import copy
import json
import os
import time
from functools import partial
from pathlib import Path

import torch

from omnilidar.checkpoints import (checkpoint_iteration, iteration_hooks, job_provenance, relative_marker,
                                   resumable_runner_args, resume_point, weights_only_hooks)
from omnilidar.devices import cpu_has_native_bf16
from omnilidar.errors import InputError
from omnilidar.generator.data import RangeImageDataset, collate, make_batch_sampler, read_domains_index, rng_for
from omnilidar.generator.checkpoint import CHECKPOINT_FORMAT, load_generator
from omnilidar.generator.diffusion import epsilon_loss
from omnilidar.generator.adversarial import build_critic, critic_loss, fooling_loss
from omnilidar.generator.distill import (compression_loss, consistency_loss, distillation_loss, progressive_pair,
                                         weighted_x0_error)
from omnilidar.generator.distribution_matching import build_fake_score, fake_score_loss, matching_loss
from omnilidar.generator.distill_steps import (calibration_samplers, compression_iterations, distillation_iterations,
                                               last_round_terms, res_blocks_per_level, round_at, round_iterations,
                                               round_steps, starts_from_teacher, student_lr, student_model,
                                               student_sampler, student_steps, teacher_sampler_steps)
from omnilidar.generator.return_decision import calibrate_returns
from omnilidar.generator.samplers import SAMPLER_NAMES
from omnilidar.generator.schedule import CosineLogSNRSchedule
from omnilidar.generator.text import load_prompt_cache, stack_prompts
from omnilidar.generator.unet import build_denoiser, count_parameters



# Keys that do not change what one training step computes: a run whose config differs
# only in these resumes the same work directory (e.g. extending ``iterations``).
_RESUMABLE_KEYS = ("iterations", "checkpoint_interval", "keep_checkpoints", "log_interval", "num_workers", "device")


def use_training_device(name: str) -> None:
    """generator.training.device: ``cpu`` hides CUDA from this process before anything asks for
    it (mmengine's Runner moves the model to CUDA whenever it sees one); ``cuda`` requires it."""
    from omnilidar.devices import resolve_device

    if name == "cpu":
        os.environ["CUDA_VISIBLE_DEVICES"] = ""
    else:
        resolve_device(name, "generator.training.device")


# Distillation keys that only calibrate the finished student (omnilidar.generator.return_decision),
# after its last step: a distillation whose settings differ only in these resumes the finished
# student of the same work directory and calibrates it again, without distilling it again.
_CALIBRATION_KEYS = ("return_calibration", "range_calibration", "calibration_sectors", "calibration_sampler",
                     "calibration_rule")


def trajectory_settings(settings: dict, distilling: bool = False) -> dict:
    """The settings that determine the training trajectory (provenance of a run); the
    distillation section, less its calibration, only where the run is a distillation. At a
    constant rate (``lr_decay: constant``) the last round's length decides nothing before the
    round ends, so ``final_round_iterations`` extends a distillation as ``iterations`` extends a
    training: a longer last round resumes the finished student's state."""
    relevant = {k: v for k, v in settings.items() if k != "sampling" and (distilling or k != "distillation")}
    relevant["training"] = {k: v for k, v in settings["training"].items() if k not in _RESUMABLE_KEYS}
    if distilling:
        dist = settings["distillation"]
        extends = ("final_round_iterations",) if dist.get("lr_decay", "constant") == "constant" else ()
        relevant["distillation"] = {k: v for k, v in dist.items() if k not in _CALIBRATION_KEYS + extends}
    return json.loads(json.dumps(relevant, sort_keys=True, default=str))


# --------------------------------------------------------------------------- model


def make_diffusion_model(denoiser, settings: dict, prompt_tokens: torch.Tensor, prompt_mask: torch.Tensor, seed: int,
                         teacher: torch.nn.Module | None = None, cpu_bf16: bool = False,
                         critic: torch.nn.Module | None = None):
    """The mmengine adapter: ``loss`` mode is :func:`omnilidar.generator.diffusion.epsilon_loss`
    with noise drawn from a generator keyed by (seed, rank, iteration).

    With a frozen ``teacher`` (the trained generator) the loss is distillation's instead
    (``settings["distillation"]``, :mod:`omnilidar.generator.distill`): a student of another architecture
    first learns the teacher's denoiser (compression), then the rounds; round 0's teacher is the
    trained generator, every later round's a frozen copy of the student as the previous round
    left it. That copy and its round are part of the model's state, so a checkpoint resumes with
    the teacher of its round. A ``critic`` adds its term to the last round and trains beside the
    student; it is part of the state too: a patch critic of the student's scans
    (``adversarial_weight``, :mod:`omnilidar.generator.adversarial`) or a fake score of them
    (``distribution_matching_weight``, :mod:`omnilidar.generator.distribution_matching`).

    ``cpu_bf16``: the loss of a model on the CPU runs under bf16 autocast (on CUDA the optimizer
    wrapper autocasts)."""
    from mmengine.dist import get_rank
    from mmengine.model import BaseModel

    class DiffusionModel(BaseModel):
        def __init__(self):
            super().__init__()
            self.denoiser = denoiser
            d = settings["diffusion"]
            self.schedule = CosineLogSNRSchedule(d["logsnr_min"], d["logsnr_max"])
            self.gamma = float(d["min_snr_gamma"])
            self.weighting = d["loss_weighting"]
            self.crop_width = settings["training"].get("crop_width")
            self.register_buffer("prompt_tokens", prompt_tokens.float(), persistent=False)
            self.register_buffer("prompt_mask", prompt_mask.bool(), persistent=False)
            self.seed = int(seed)
            self.iteration = 0  # set by IterationHook before every step
            self.teacher = teacher
            if teacher is not None:
                teacher.requires_grad_(False)
                self.round_teacher = copy.deepcopy(denoiser).requires_grad_(False)
                self.register_buffer("teacher_round", torch.zeros((), dtype=torch.long))
                self.compression = compression_iterations(settings)
            self.critic = critic

        def train(self, mode: bool = True):
            super().train(mode)
            if self.teacher is not None:
                self.teacher.eval()
                self.round_teacher.eval()
            return self

        def train_step(self, data, optim_wrapper):
            """With a critic (two optimizers), the student steps on its losses, then the critic
            ``critic_updates`` times on its own, each time on its loss computed again on the
            student's scans of this step (a fake score's with fresh noise; the two time-scale
            update rule of DMD2)."""
            if self.critic is None:
                return super().train_step(data, optim_wrapper)
            losses = self._run_forward(self.data_preprocessor(data, True), mode="loss")
            critic_loss_of = losses.pop("loss_critic", None)  # the last round's only
            student_loss, log_vars = self.parse_losses(losses)
            optim_wrapper["denoiser"].update_params(student_loss)
            if critic_loss_of is not None:
                for _ in range(int(settings["distillation"]["critic_updates"])):
                    critic_term = critic_loss_of()
                    optim_wrapper["critic"].update_params(critic_term)
                log_vars["loss_critic"] = critic_term.detach()
            return log_vars

        def forward(self, image=None, domain=None, prompt=None, mode: str = "loss"):
            if mode != "loss":
                raise ValueError(f"DiffusionModel supports mode='loss' only, got {mode!r}")
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=cpu_bf16 and image.device.type == "cpu"):
                return self.loss(image, domain, prompt)

        def loss(self, image, domain, prompt):
            gen = torch.Generator(device=image.device)
            gen.manual_seed(int(rng_for(self.seed, get_rank(), self.iteration).integers(2**63 - 1)))
            tokens, mask = self.prompt_tokens[prompt], self.prompt_mask[prompt]
            if self.teacher is None:
                loss = epsilon_loss(self.denoiser, image, domain, tokens, mask, self.schedule, self.gamma, gen,
                                    crop_width=self.crop_width, weighting=self.weighting)
                return {"loss": loss}
            dist = settings["distillation"]
            args = (image, domain, tokens, mask, self.schedule)
            if self.iteration < self.compression:  # a narrower student learns the trained generator first
                loss = compression_loss(self.denoiser, self.teacher, *args, int(dist["teacher_steps"]), gen,
                                        crop_width=self.crop_width, spacing=dist["spacing"], huber_c=dist["huber_c"])
                return {"loss": loss}
            if dist["method"] == "consistency":  # the trained generator teaches throughout
                loss = consistency_loss(self.denoiser, self.teacher, *args, int(dist["teacher_steps"]), gen,
                                        crop_width=self.crop_width, spacing=dist["spacing"], huber_c=dist["huber_c"],
                                        substeps=int(dist["teacher_substeps"]))
                return {"loss": loss}
            round_index = round_at(dist, self.iteration - self.compression)
            if int(self.teacher_round) < round_index:  # a new round: the student becomes the teacher
                self.round_teacher.load_state_dict(self.denoiser.state_dict())
                self.teacher_round.fill_(round_index)
            round_teacher = self.round_teacher if round_index else self.teacher
            # Only the trained generator takes substeps: a round's student has learnt its own grid only.
            substeps = 1 if round_index else int(dist["teacher_substeps"])
            if self.critic is None or round_index < int(dist["rounds"]) - 1:
                loss = distillation_loss(self.denoiser, round_teacher, *args, round_steps(dist, round_index), gen,
                                         crop_width=self.crop_width, spacing=dist["spacing"], huber_c=dist["huber_c"],
                                         substeps=substeps)
                return {"loss": loss}
            # The last round adds a term on the student's scans as a set, from a second network.
            real, extra, x0, target, l_t = progressive_pair(self.denoiser, round_teacher, *args,
                                                            round_steps(dist, round_index), gen,
                                                            crop_width=self.crop_width, spacing=dist["spacing"],
                                                            substeps=substeps)
            regression = weighted_x0_error(x0, l_t, target, dist["huber_c"])
            # The term's weight is relative to the unweighted regression; the regression itself may
            # weigh less (0: the term alone). "x0_regression" is logged, not summed into the loss.
            losses = {"loss": float(dist["last_round_regression_weight"]) * regression,
                      "x0_regression": regression.detach()}
            # The second network's loss is returned uncomputed: train_step draws it per update.
            scans = x0.detach()
            if last_round_terms(dist) == ["adversarial_weight"]:  # a critic against the training scans
                return {**losses,
                        "loss_fooling": fooling_loss(self.critic, x0, domain, regression,
                                                     float(dist["adversarial_weight"])),
                        "loss_critic": lambda: critic_loss(self.critic, real, scans.clamp(-1.0, 1.0), domain)}
            # a fake score of the student's scans against the trained generator's
            matching = matching_loss(self.teacher, self.critic, x0, domain, tokens, mask, self.schedule, gen,
                                     regression, float(dist["distribution_matching_weight"]), extra)
            return {**losses, "loss_matching": matching,
                    "loss_critic": lambda: fake_score_loss(self.critic, scans, domain, tokens, mask, self.schedule,
                                                           self.gamma, gen, self.weighting, extra)}

    return DiffusionModel()


# --------------------------------------------------------------------------- hooks


def make_hooks(settings: dict, domain_names: list[str], seed: int, provenance: dict, cost=None, lr_at=None) -> list:
    """Our custom hooks: weights-only-safe checkpoints (+ resolved config) and the step counter;
    with ``lr_at`` (step -> learning rate) the denoiser's rate is set before every step."""
    from mmengine.hooks import Hook
    from mmengine.model import is_model_wrapper

    class IterationHook(Hook):
        """Tell the model the global step (its noise generator is keyed by it)."""

        priority = "VERY_HIGH"

        def before_train_iter(self, runner, batch_idx: int, data_batch=None) -> None:
            model = runner.model.module if is_model_wrapper(runner.model) else runner.model
            model.iteration = runner.iter
            if lr_at is not None:
                wrapper = runner.optim_wrapper
                wrapper = wrapper["denoiser"] if "denoiser" in getattr(wrapper, "optim_wrappers", {}) else wrapper
                for group in wrapper.optimizer.param_groups:
                    group["lr"] = lr_at(runner.iter)

    meta = {"config": settings, "domains": list(domain_names), "seed": int(seed), "provenance": provenance}
    hooks = [*weights_only_hooks(meta), IterationHook()]
    if cost is not None:  # each checkpoint carries the training cost so far, resumed parts included

        class CostHook(Hook):
            priority = "VERY_HIGH"

            def before_save_checkpoint(self, runner, checkpoint: dict) -> None:
                meta["cost"] = cost()

        hooks.append(CostHook())
    return hooks


# --------------------------------------------------------------------------- entry point




def ema_hook(training: dict):
    """mmengine's EMAHook for the ``training`` settings: constant decay, or with
    ``ema_warmup`` > 0 a momentum annealed from 1 down to 1 - ema_decay."""
    from mmengine.hooks import EMAHook

    momentum = 1.0 - training["ema_decay"]
    if training["ema_warmup"] > 0:
        return EMAHook(ema_type="MomentumAnnealingEMA", momentum=momentum, gamma=training["ema_warmup"])
    return EMAHook(momentum=momentum)


def state_digest(state: dict) -> str:
    """sha256 of a state dict's tensors in key order."""
    import hashlib

    h = hashlib.sha256()
    for key in sorted(state):
        h.update(key.encode())
        h.update(state[key].detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def _log(message: str) -> None:
    print(message, flush=True)


def _dist_info() -> tuple[str, int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    return ("pytorch" if world > 1 else "none"), rank, world


def init_distributed(world: int) -> None:
    """Join the process group torchrun set up (NCCL on CUDA, gloo on CPU) before the Runner:
    mmengine's own set-up calls torch.cuda.set_device, which a CPU-only torch lacks."""
    import torch.distributed as dist

    if world <= 1 or dist.is_initialized():
        return
    if torch.cuda.is_available():
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")


def agreed_resume_point(run_dir: Path, provenance: dict, iterations: int, world: int) -> Path | None:
    """:func:`resume_point` decided by rank 0 alone (it may remove a stale work dir);
    the other ranks wait for its answer and resume the same checkpoint."""
    if world <= 1:
        return resume_point(run_dir, provenance, iterations, log=_log)
    import torch.distributed as dist

    decision = [None]
    if dist.get_rank() == 0:
        found = resume_point(run_dir, provenance, iterations, log=_log)
        decision = [str(found) if found else None]
    dist.broadcast_object_list(decision, src=0)
    return Path(decision[0]) if decision[0] else None


def check_crop_width(settings: dict) -> None:
    """training.crop_width must survive the UNet's downsampling (a crop as wide as the
    image or wider trains on full images)."""
    crop, width = settings["training"].get("crop_width"), settings["range_image"]["width"]
    down = 2 ** (len(settings["model"]["channel_multipliers"]) - 1)
    if crop is not None and crop < width and crop % down:
        raise InputError(None, f"generator.training.crop_width {crop}: must be divisible by {down} "
                               f"(the UNet halves the width {down.bit_length() - 1} times)")


def check_loss_weighting(settings: dict) -> None:
    """v_uniform trains the network's own v output, which only a v_skip head has."""
    d = settings["diffusion"]
    if d["loss_weighting"] == "v_uniform" and d["epsilon_output"] != "v_skip":
        raise InputError(None, f"generator.diffusion.loss_weighting v_uniform needs epsilon_output v_skip "
                               f"(the head then outputs v), not {d['epsilon_output']!r}")


def teacher_weights(path: str | Path, settings: dict, names: list[str], cache: dict) -> torch.nn.Module:
    """The trained generator to distill, checked against the student's settings and inputs."""
    frozen, payload = load_generator(path)
    for key in ("range_image", "model", "diffusion"):
        if payload["config"][key] != settings[key]:
            raise InputError(path, f"the teacher was trained with other generator.{key} settings than the student's")
    if payload["domains"] != names or int(payload["text"]["dim"]) != int(cache["dim"]):
        raise InputError(path, "the teacher was trained on other domains or prompt embeddings than the student's")
    if payload.get("student"):
        raise InputError(path, "is already a distilled student; distill the trained generator")
    return frozen


def check_student_blocks(settings: dict) -> None:
    """One clear error for a ``student_res_blocks`` the student cannot take from its teacher: a list
    of another length than the UNet's levels, or more blocks at a level than the teacher has there."""
    given = settings["distillation"]["student_res_blocks"]
    try:
        own, teacher = res_blocks_per_level(student_model(settings)), res_blocks_per_level(settings["model"])
    except ValueError as err:
        raise InputError(None, f"generator.distillation.student_res_blocks {given}: {err}") from None
    over = [lv for lv, (s, t) in enumerate(zip(own, teacher)) if s > t]
    if over:
        raise InputError(None, f"generator.distillation.student_res_blocks {given} exceeds the trained generator's "
                               f"model.num_res_blocks {settings['model']['num_res_blocks']} at level {over[0]}: a "
                               "student keeps some of its teacher's blocks")


def check_calibration_sampler(dist: dict | None) -> None:
    """One clear error for a ``calibration_sampler`` that names no sampler, or that has no
    return calibration's scans to sample (unset: nothing to check)."""
    if dist is None or not dist.get("calibration_sampler"):
        return
    candidates = calibration_samplers(dist)
    for name, steps in candidates:
        if name not in SAMPLER_NAMES:
            raise InputError(None, f"generator.distillation.calibration_sampler: unknown sampler {name!r}; choose from "
                                   f"{', '.join(SAMPLER_NAMES)}")
    if len(set(candidates)) < len(candidates):
        raise InputError(None, "generator.distillation.calibration_sampler names a setting twice")
    if not dist["return_calibration"]:
        raise InputError(None, f"generator.distillation.calibration_sampler {', '.join(f'{n}:{k}' for n, k in candidates)} "
                               "samples the return calibration's scans: set return_calibration > 0")
    if len(candidates) > 1 and dist.get("calibration_rule") == "first_holding" and int(dist["return_calibration"]) < 2:
        raise InputError(None, "generator.distillation.calibration_rule first_holding scores each candidate's scans "
                               "in seed groups: set return_calibration >= 2")


def check_last_round_terms(dist: dict | None) -> None:
    """One clear error for a last-round term (a critic or distribution matching) that cannot run:
    both at once, with consistency distillation (no last round), or on several processes."""
    if dist is None:
        return
    terms = last_round_terms(dist)
    regression_weight = float(dist.get("last_round_regression_weight", 1.0))
    if regression_weight != 1.0 and not terms:
        raise InputError(None, f"generator.distillation.last_round_regression_weight {regression_weight} weighs the "
                               "regression beside a last-round term: set adversarial_weight or "
                               "distribution_matching_weight, or leave it at 1")
    if len(terms) > 1:
        raise InputError(None, "generator.distillation: adversarial_weight and distribution_matching_weight each "
                               "train a second network in the last round; set one of them")
    if terms and dist["method"] != "progressive":
        raise InputError(None, f"generator.distillation.{terms[0]} {dist[terms[0]]} needs method progressive "
                               f"(its last round), not {dist['method']}")
    if terms and _dist_info()[2] > 1:
        raise InputError(None, f"generator.distillation.{terms[0]}: its second network trains on one process; "
                               "distil on one device (its second optimizer has no multi-process step here)")


def train_generator(
    settings: dict,
    domains_index: str | Path,
    prompts_path: str | Path,
    work_dir: str | Path,
    out: str | Path,
    seed: int = 0,
    until: int | None = None,
    teacher: str | Path | None = None,
    choose_calibration=None,
) -> dict:
    """Train (or resume) the generator and write the final EMA weights + config to ``out``.

    ``teacher``: a trained generator checkpoint to distill instead (``settings["distillation"]``,
    :mod:`omnilidar.generator.distill`): the student starts from its weights (with fewer
    ``student_res_blocks``, from those of the blocks it keeps; at another ``student_channels``, from
    scratch), learns the trained generator's denoiser for ``compression_iterations`` first where its
    architecture differs, trains its rounds' steps (:func:`~omnilidar.generator.distill_steps.round_iterations`)
    at the distillation learning rate, without EMA, and
    ``out`` records the DDIM steps it samples in (``payload["student"]``) and the student's own
    model settings.

    ``choose_calibration``: with several ``calibration_sampler`` candidates, the rule that picks
    each domain's (:func:`~omnilidar.generator.return_decision.calibrate_returns`' ``choose``).

    ``until``: one segment of a chain (see ``rules/generator.smk``): train only up to that
    iteration, leave the resumable state (checkpoint at ``until``) in ``work_dir`` and write a
    JSON record of the segment to ``out``; the next segment, or the full run, resumes from it.
    The learning-rate schedule depends on the warm-up only, so a chain ends with the weights of
    one uninterrupted run. Returns a small summary (iterations, parameters, work dir). ``out``
    is written atomically on the main process only.
    """
    from mmengine.dist import is_main_process
    from mmengine.hooks import EMAHook
    from mmengine.runner import Runner

    from omnilidar.io.atomic import atomic_path

    tr = settings["training"]
    dist = settings["distillation"] if teacher is not None else None
    if dist is not None and dist.get("seed") is not None:  # a distillation seed of its own, else the run's
        seed = int(dist["seed"])
    if dist is not None:
        check_student_blocks(settings)
    iterations = tr["iterations"] if dist is None else distillation_iterations(settings)
    if until is not None and not 0 < until < iterations:
        raise InputError(None, f"--until {until} must lie between 0 and the {iterations} iterations to train")
    stop = until or iterations
    if dist is not None and (dist["teacher_steps"] >> dist["rounds"]) << dist["rounds"] != dist["teacher_steps"]:
        raise InputError(None, f"generator.distillation: teacher_steps {dist['teacher_steps']} cannot be halved "
                               f"{dist['rounds']} times")
    check_last_round_terms(dist)
    if dist is not None and dist["range_calibration"] and not dist["return_calibration"]:
        raise InputError(None, f"generator.distillation.range_calibration {dist['range_calibration']} maps the "
                               "student's returns on the return calibration's scans: set return_calibration > 0")
    if dist is not None and settings["range_image"]["width"] % int(dist.get("calibration_sectors") or 1):
        raise InputError(None, f"generator.distillation.calibration_sectors {dist['calibration_sectors']} does not "
                               f"split range_image.width {settings['range_image']['width']} into equal azimuth sectors")
    check_calibration_sampler(dist)
    if dist is not None and len(calibration_samplers(dist)) > 1 and choose_calibration is None:
        raise InputError(None, "generator.distillation.calibration_sampler names candidates: the distillation "
                               "needs the rule that chooses between them (omnilidar distill-generator passes it)")
    use_training_device(tr["device"])
    h, w = settings["range_image"]["height"], settings["range_image"]["width"]
    check_crop_width(settings)
    check_loss_weighting(settings)
    domains = read_domains_index(domains_index)
    names = list(domains)
    cache = load_prompt_cache(prompts_path)
    tokens, mask, spans = stack_prompts(cache, names)
    dataset = RangeImageDataset(domains, (h, w), spans)

    run_dir = Path(work_dir)
    launcher, rank, world = _dist_info()
    init_distributed(world)
    trajectory = trajectory_settings(settings, distilling=dist is not None)
    if world > 1:  # each rank draws its own batches: the trajectory depends on how many there are
        trajectory["world_size"] = world
    inputs = {"domains": domains_index, "prompts": prompts_path} | ({"teacher": teacher} if dist else {})
    provenance = job_provenance("train-generator" if dist is None else "distill-generator", trajectory, seed, inputs)
    resume_from = agreed_resume_point(run_dir, provenance, stop, world)
    skip = checkpoint_iteration(resume_from) if resume_from else 0

    sampler = make_batch_sampler(
        tr["strategy"], dataset, tr["batch_size"], seed, tr["single_domain"], rank=rank, world_size=world, skip=skip
    )
    loader = torch.utils.data.DataLoader(
        dataset, batch_sampler=sampler, collate_fn=collate, num_workers=tr["num_workers"],
        persistent_workers=tr["num_workers"] > 0,
    )

    # Weight init from an explicit seed without touching the global RNG state.
    init_seed = int(rng_for(seed, 0x1D17).integers(2**63 - 1))
    # A student's own settings: the trained generator's, at the student's width.
    own = settings if dist is None else {**settings, "model": student_model(settings)}
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(init_seed)
        denoiser = build_denoiser(own, cache["dim"], len(names))
    frozen = None
    if dist is not None:
        frozen = teacher_weights(teacher, settings, names, cache)
        if starts_from_teacher(settings):  # every tensor of the student is one of the teacher's
            teacher_state = frozen.state_dict()
            denoiser.load_state_dict({name: teacher_state[name] for name in denoiser.state_dict()})
    if settings["diffusion"]["prior"] == "domain_mean":  # a student centres on its teacher's means
        denoiser.set_prior_mean(dataset.domain_means() if frozen is None else frozen.prior_mean)
    cuda = torch.cuda.is_available()
    # bf16 autocast on CUDA through the optimizer wrapper; on a CPU only where it multiplies bf16
    # natively: racing both precisions at once, bf16 took 0.8x the fp32 time in the median, though
    # the races disagreed (benchmarks/bench_train_precision.py, docs/benchmarks.md).
    # Distillation always runs in float32: its losses compare x0 estimates at every time, including
    # the noisy end where an epsilon network's bf16 rounding becomes an x0 error larger than the data
    # (omnilidar.generator.schedule.BF16_MIN_LOGSNR; the students distilled in bf16 learnt from it).
    bf16 = bool(tr["bf16"]) and dist is None
    cpu_bf16 = bf16 and not cuda and cpu_has_native_bf16()
    critic = None  # the last round's second network, where a term needs one
    if dist is not None and last_round_terms(dist) == ["adversarial_weight"]:
        critic = build_critic(denoiser.cfg.in_channels, len(names), int(rng_for(seed, 0xC217).integers(2**63 - 1)))
    elif dist is not None and last_round_terms(dist) == ["distribution_matching_weight"]:
        critic = build_fake_score(frozen)
    model = make_diffusion_model(denoiser, settings, tokens, mask, seed, teacher=frozen, cpu_bf16=cpu_bf16,
                                 critic=critic)

    lr = tr["lr"] if dist is None else dist["lr"]
    optimizer = dict(type="AdamW", lr=lr, betas=tuple(tr["betas"]), weight_decay=tr["weight_decay"])
    optim_wrapper = dict(type="OptimWrapper", optimizer=optimizer)
    if cuda and bf16:
        optim_wrapper = dict(type="AmpOptimWrapper", dtype="bfloat16", optimizer=optimizer)
    if tr["grad_clip"] > 0:
        optim_wrapper["clip_grad"] = dict(max_norm=tr["grad_clip"])
    if critic is not None:  # two optimizers: the second network's is its own, unclipped, at the usual GAN betas
        from mmengine.optim import OptimWrapper

        student_settings = {k: v for k, v in optimizer.items() if k != "type"}  # the AdamW above
        optim_wrapper = {
            "denoiser": OptimWrapper(torch.optim.AdamW(denoiser.parameters(), **student_settings),
                                     clip_grad=optim_wrapper.get("clip_grad")),
            "critic": OptimWrapper(torch.optim.Adam(critic.parameters(), lr=float(dist["critic_lr"]),
                                                    betas=(0.0, 0.99))),
        }
    # the student's rate, per step (a function of the step, so resumes take the same rates)
    student_lr_at = None if dist is None or dist["lr_decay"] == "constant" else partial(student_lr, settings)
    param_scheduler = None
    if tr["warmup_iters"] > 0 and dist is None:  # a student starts from trained weights
        param_scheduler = [
            # mmengine's LinearLR reaches end_factor at step end - 1
            dict(type="LinearLR", start_factor=1e-3, by_epoch=False, begin=0, end=tr["warmup_iters"] + 1)
        ]

    # What training cost so far (for the budget study): the resumed checkpoint's cost plus this run's.
    prior = {"train_seconds": 0.0, "train_cpu_seconds": 0.0}
    if resume_from:
        stored = torch.load(resume_from, map_location="cpu", weights_only=True).get("meta", {})
        prior.update(stored.get("omnilidar", {}).get("cost", {}))
    wall0, cpu0 = time.perf_counter(), time.process_time()

    def training_cost() -> dict:
        return {"train_seconds": round(prior["train_seconds"] + time.perf_counter() - wall0, 2),
                "train_cpu_seconds": round(prior["train_cpu_seconds"] + time.process_time() - cpu0, 2)}

    runner = Runner(
        model=model,
        work_dir=str(run_dir),
        train_dataloader=loader,
        train_cfg=dict(by_epoch=False, max_iters=stop, val_interval=stop + 1),
        optim_wrapper=optim_wrapper,
        param_scheduler=param_scheduler,
        default_hooks=iteration_hooks(tr["log_interval"], tr["checkpoint_interval"], tr["keep_checkpoints"]),
        custom_hooks=[*([ema_hook(tr)] if dist is None else []),
                      *make_hooks(own, names, seed, provenance, training_cost, lr_at=student_lr_at)],
        launcher=launcher,
        # A CPU module takes no device_ids (mmengine's default passes LOCAL_RANK).
        cfg=None if cuda or world == 1 else dict(model_wrapper_cfg=dict(
            type="MMDistributedDataParallel", device_ids=None, broadcast_buffers=False)),
        env_cfg=dict(cudnn_benchmark=False, dist_cfg=dict(backend="nccl" if cuda else "gloo")),
        **resumable_runner_args(resume_from, seed, tr["log_interval"]),
    )
    what = "generator" if dist is None else (
        f"student of {teacher} ({dist['method']} distillation, {teacher_sampler_steps(dist)} -> {student_steps(dist)} "
        f"DDIM steps, rounds of {round_iterations(dist)} iterations"
        + (f" after {compression_iterations(settings)} of compression to base_channels "
           f"{own['model']['base_channels']}, residual blocks per level {own['model']['num_res_blocks']})"
           if compression_iterations(settings) else ")"))
    runner.logger.info(
        f"omnilidar {what}: {count_parameters(denoiser) / 1e6:.2f} M parameters, domains {names}, "
        f"{len(dataset)} scans, strategy {tr['strategy']}, {iterations} iterations"
        + (", bf16 autocast on the CPU" if cpu_bf16 else "")
        + (f" (this segment up to {stop})" if until else "")
        + (f", resuming at iteration {skip} from {resume_from.name}" if resume_from else ", from scratch")
    )
    runner.train()
    cost = training_cost()
    if is_main_process():
        relative_marker(run_dir)

    if dist is None:
        final = next(h for h in runner._hooks if isinstance(h, EMAHook)).ema_model.module.denoiser
    else:
        final = denoiser
    state = {k: v.detach().cpu().clone() for k, v in final.state_dict().items()}
    summary = {
        "iterations": int(runner.iter),
        # Same on every DDP rank when gradients were averaged (tests compare the ranks').
        "weights_digest": state_digest(state),
        "parameters": count_parameters(denoiser),
        "work_dir": str(run_dir),
        "resumed_from": skip,
        "precision": "bf16 autocast" if cuda and bf16 or cpu_bf16 else "fp32",
        **cost,
    }
    if until is not None:
        if is_main_process():
            record = {"segment_until": until, "provenance": provenance,
                      **{k: v for k, v in summary.items() if k != "work_dir"}}
            with atomic_path(out) as tmp:
                Path(tmp).write_text(json.dumps(record, indent=1, default=str))
        runner.logger.info(f"segment up to iteration {until} done; state in {run_dir}, record {out}")
        return summary
    if is_main_process():
        payload = {
            "format": CHECKPOINT_FORMAT,
            "state_dict": state,
            "config": own,
            "domains": names,
            # Per-domain image geometry (sensor field of view, pitch, range limits)
            # from the domains index, for back-projecting samples.
            "domain_range_images": {n: domains[n]["range_image"] for n in names if "range_image" in domains[n]},
            "text": {"encoder": cache["encoder"], "model": cache["model"], "dim": int(cache["dim"]),
                     "model_files_digest": cache.get("model_files_digest")},
            "seed": int(seed),
            "provenance": provenance,
            **{k: v for k, v in summary.items() if k != "work_dir"},
        }
        if dist is not None:
            payload["student"] = {"sampler": student_sampler(dist), "steps": student_steps(dist),
                                  "teacher": str(teacher), "teacher_steps": int(dist["teacher_steps"]),
                                  "teacher_substeps": int(dist["teacher_substeps"]), "rounds": int(dist["rounds"]),
                                  "method": dist["method"], "return_calibration": int(dist["return_calibration"]),
                                  "range_calibration": int(dist["range_calibration"]),
                                  "calibration_sectors": int(dist.get("calibration_sectors") or 1),
                                  "calibration_rule": dist.get("calibration_rule") or "closest",
                                  "calibration_sampler": ", ".join(f"{n}:{k}" for n, k in calibration_samplers(dist))}
            if int(dist["return_calibration"]):
                calibration = calibrate_returns(final, frozen, payload, cache, seed, choose_calibration,
                                                log=runner.logger.info)
                choice = calibration.pop("calibration_choice")
                if len(calibration_samplers(dist)) > 1:  # which candidate each domain's maps were fitted on
                    payload["student"]["calibration_sampler"] = choice
                payload.update(calibration)
        with atomic_path(out) as tmp:
            torch.save(payload, tmp)
    runner.logger.info(f"wrote {out}")
    return summary
