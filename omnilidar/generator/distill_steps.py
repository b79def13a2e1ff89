"""How long a distillation runs and how many steps its student samples in, from the settings alone
(no torch), so the workflow can plan and size the job before it runs
(:mod:`omnilidar.generator.distill` trains it)."""

from __future__ import annotations

import math
from bisect import bisect_right
from itertools import accumulate


def res_blocks_per_level(model: dict) -> list[int]:
    """Residual blocks at each UNet level (level 0 at full resolution) of ``model`` settings, whose
    ``num_res_blocks`` is one number for every level or a list of one per level."""
    blocks, levels = model["num_res_blocks"], len(model["channel_multipliers"])
    if isinstance(blocks, int):
        return [blocks] * levels
    if len(blocks) != levels:
        raise ValueError(f"num_res_blocks {list(blocks)} has {len(blocks)} entries for {levels} UNet levels")
    return [int(b) for b in blocks]


def student_model(settings: dict) -> dict:
    """The student's model settings: the trained generator's, at ``distillation.student_channels``
    and ``student_res_blocks`` (one number, or one per level) where those are set."""
    d = settings["distillation"]
    model = dict(settings["model"])
    if d.get("student_channels") is not None:
        model["base_channels"] = int(d["student_channels"])
    if d.get("student_res_blocks") is not None:
        blocks = d["student_res_blocks"]
        model["num_res_blocks"] = int(blocks) if isinstance(blocks, int) else [int(b) for b in blocks]
    return model


def same_architecture(a: dict, b: dict) -> bool:
    """Whether two model settings build the same network (a list of equal residual blocks per level
    is the same as their one number)."""
    if isinstance(a["num_res_blocks"], int) and isinstance(b["num_res_blocks"], int):
        return a == b
    return {**a, "num_res_blocks": res_blocks_per_level(a)} == {**b, "num_res_blocks": res_blocks_per_level(b)}


def starts_from_teacher(settings: dict) -> bool:
    """Whether the student starts from its teacher's weights: at the teacher's width it does (a
    student with fewer residual blocks per level keeps the first ones of every level); a narrower
    one starts from scratch."""
    return student_model(settings)["base_channels"] == settings["model"]["base_channels"]


def compression_iterations(settings: dict) -> int:
    """Steps in which a student of another architecture (width or residual blocks) learns the trained
    generator's denoiser first."""
    narrow = not same_architecture(student_model(settings), settings["model"])
    return int(settings["distillation"]["compression_iterations"]) if narrow else 0


def distillation_iterations(settings: dict) -> int:
    """Optimizer steps of the whole distillation (compression, then the rounds)."""
    return compression_iterations(settings) + sum(round_iterations(settings["distillation"]))


def round_iterations(distillation: dict) -> list[int]:
    """Optimizer steps of each round: ``iterations_per_round``, the last one
    ``final_round_iterations`` where that is set (the last halving, to one or two steps, is the
    hardest for the student to learn)."""
    d = distillation
    rounds = [int(d["iterations_per_round"])] * int(d["rounds"])
    if d.get("final_round_iterations") is not None:
        rounds[-1] = int(d["final_round_iterations"])
    return rounds


# A last-round step with its second network, in steps without one, and what each further update
# of that network (critic_updates) adds (measured in the job logs of the pruned 1-step student on
# 2 CPUs, docs/results.md): distribution matching runs two passes of the trained generator and
# the fake score's forward and backward, 2.8 s against 1.2 s, and each further fake-score update
# 0.83 s (4.5 s at 3). A critic step took 1.6 s; its further updates were not timed apart and are
# counted at the critic's whole extra cost.
LAST_ROUND_STEP_COST = {"adversarial_weight": (1.35, 0.35), "distribution_matching_weight": (2.3, 0.7)}


def last_round_terms(distillation: dict) -> list[str]:
    """The last-round terms switched on (their weight > 0), each training a second network:
    ``adversarial_weight`` (a critic) and ``distribution_matching_weight`` (a fake score)."""
    return [key for key in LAST_ROUND_STEP_COST if float(distillation.get(key) or 0) > 0]


def last_round_extra_steps(distillation: dict) -> float:
    """What a last-round term's second network (updated ``critic_updates`` times a step) adds to
    the distillation, in optimizer steps without one."""
    last = round_iterations(distillation)[-1]
    more = int(distillation.get("critic_updates") or 1) - 1
    return sum(last * (LAST_ROUND_STEP_COST[key][0] - 1 + more * LAST_ROUND_STEP_COST[key][1])
               for key in last_round_terms(distillation))


def teacher_sampler_steps(distillation: dict) -> int:
    """DDIM steps of the trained generator's sampler that the student learns: ``teacher_steps``,
    each taken in ``teacher_substeps`` steps of a finer grid."""
    return int(distillation["teacher_steps"]) * int(distillation.get("teacher_substeps") or 1)


def calibration_samplers(distillation: dict) -> list[tuple[str, int]]:
    """[(sampler, steps)] of the trained generator on whose scans the finished student's returns and
    ranges are calibrated: ``calibration_sampler`` where set (one setting, or candidates of which
    each domain takes the one whose scans lie closest to its training scans), else the DDIM path the
    student learnt (on the distillation's spacing, ``teacher_steps`` x ``teacher_substeps``)."""
    chosen = distillation.get("calibration_sampler")
    if chosen:
        return [(str(c["sampler"]), int(c["steps"])) for c in (chosen if isinstance(chosen, list) else [chosen])]
    return [(student_sampler(distillation), teacher_sampler_steps(distillation))]


# One more pass of the trained generator, in distillation steps without it: measured in the job log
# of the pruned 1-step student at teacher_substeps 4 on 2 CPUs (docs/results.md), a first-round
# step took 3.1 s against 1.2 s, six more passes. A full-width student's own passes weigh more, so
# there a teacher pass costs less than this (about a fifth of a step: 5 passes a step).
TEACHER_PASS_COST = 0.26


def teacher_substep_extra_steps(distillation: dict) -> float:
    """What the trained generator's further substeps add to the distillation, in its optimizer
    steps: each further substep is one more teacher pass, twice per step of progressive
    distillation's first round (the only round the trained generator teaches), once per step of
    consistency distillation's."""
    more = int(distillation.get("teacher_substeps") or 1) - 1
    if distillation["method"] == "consistency":
        return sum(round_iterations(distillation)) * more * TEACHER_PASS_COST
    return round_iterations(distillation)[0] * 2 * more * TEACHER_PASS_COST


def student_lr(settings: dict, step: int) -> float:
    """The student's learning rate at optimizer step ``step`` of the whole distillation: ``lr``
    throughout (``lr_decay: constant``), or annealed from ``lr`` towards 0 on a half cosine within
    each phase (compression, then every round: ``cosine``), so that each round's teacher and the
    finished student are a settled iterate rather than the last of a constant-rate walk. A function
    of the step alone, so a resumed distillation takes the same rates."""
    d = settings["distillation"]
    lr = float(d["lr"])
    if d.get("lr_decay", "constant") == "constant":
        return lr
    bounds = sorted({0, *accumulate([compression_iterations(settings), *round_iterations(d)])})
    phase = min(bisect_right(bounds, step) - 1, len(bounds) - 2)
    start, end = bounds[phase], bounds[phase + 1]
    return lr * 0.5 * (1.0 + math.cos(math.pi * min(step - start, end - start) / (end - start)))


def round_at(distillation: dict, step: int) -> int:
    """The round (0-based) that optimizer step ``step`` of the rounds (counted after compression)
    belongs to; steps past the last round count as the last round."""
    ends = list(accumulate(round_iterations(distillation)))
    return min(bisect_right(ends, step), len(ends) - 1)


def student_steps(distillation: dict) -> int:
    """DDIM steps of the finished student."""
    return int(distillation["teacher_steps"]) >> int(distillation["rounds"])


def student_sampler(distillation: dict) -> str:
    """The sampler name of the finished student: DDIM on the spacing it was distilled on."""
    spacing = distillation["spacing"]
    return "ddim" if spacing == "uniform" else f"ddim_{spacing}"


def round_steps(distillation: dict, round_index: int) -> int:
    """DDIM steps the student of round ``round_index`` (0-based) learns to sample in."""
    return int(distillation["teacher_steps"]) >> (int(round_index) + 1)
