"""Which teacher setting each domain's student calibration should target, and whether a rule that
never sees the check's scans finds it.

A student calibrated on one candidate setting in every domain is checked against the held-out sets
(``omnilidar sampler-tradeoff``); that says, per domain, which candidates hold both metrics. The
rules choose per domain without those scans, each against the domain's training scans and against
the held-out scans the check does not use (``--check-scans`` onwards):

- ``closest``: the candidate whose teacher scans lie closest (``calibration_rule: closest``, the
  distillation's default);
- ``first holding``: the first candidate whose teacher scans hold the best candidate of each metric
  by the check's rule (``calibration_rule: first_holding``);
- ``check mirrored``: the candidate whose calibrated student lies least far over the teacher's best
  setting of each metric, in units of two standard deviations over seed groups (the student check
  itself, on other scans).

    python benchmarks/measure_calibration_choice.py --teacher data/generator/full/model.pt \\
        --prompts data/generator/prompts.pt --training data/domains/index.json --heldout heldout/index.json \\
        --calibrated ddpm:32=a.pt --checked ddpm:32=a.json \\
        --calibrated unipc_logsnr:4=b.pt --checked unipc_logsnr:4=b.json --out choice.json
    python benchmarks/measure_calibration_choice.py --plot "seed 0=choice.json" --figure choice.png

The teacher's scans are those the calibration draws (its seeds, ``return_calibration`` per
domain), kept in ``--cache``; the students draw ``--student-scans`` on sampling seed ``--seed``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

GROUPS = 4  # seed groups the mirrored check scores (of the teacher's calibration scans and the student's)
WHERE = ("training", "held-out unused")
RULES = tuple(f"{rule}, {where}" for where in WHERE for rule in ("closest", "first holding", "check mirrored"))


def label_of(setting: dict) -> str:
    return f"{setting['sampler']}:{setting['steps']}"


def held_both(check: dict, domain: str) -> bool:
    """Whether a student check (a sampler-tradeoff result) held every deciding metric in ``domain``."""
    sc = check["student_check"]
    return all(sc["metrics"][m]["per_domain"][domain]["held"] for m in sc["decided_by"])


def mirrored_excess(student: dict, teachers: dict, targets: dict) -> float:
    """The worst, over metrics, of the student's excess over that metric's target teacher setting in
    units of two standard deviations (``excess_in_spreads``): at most 1 holds. ``student`` and
    ``teachers[label]``: group scores ({metric, metric_std}); ``targets``: {metric: label}."""
    from omnilidar.metrics.generation import excess_in_spreads

    return max(excess_in_spreads(student, teachers[t], m) for m, t in targets.items())


def group_stats(real, images: np.ndarray, spec) -> dict:
    """BEV JSD and MMD over GROUPS disjoint groups of ``images`` scored against ``real``."""
    from omnilidar.metrics.generation import group_scores, set_features

    return group_scores(real, set_features(images, spec, {}, 8), {}, GROUPS, ["JSD", "MMD"])


def teacher_scans(teacher, payload: dict, prompts: dict, domain: str, label: str, cache: Path) -> np.ndarray:
    """The teacher's calibration scans of ``domain`` with setting ``label``, as the distillation draws
    them (``calibration_scans``), cached."""
    from omnilidar.generator.return_decision import calibration_scans

    scans, seed = int(payload["student"]["return_calibration"]), int(payload["seed"])
    how, steps = label.split(":")
    path = cache / f"{how}_{steps}_{domain}_n{scans}_s{seed}.npy"
    if path.is_file():
        return np.load(path)
    import torch

    with torch.no_grad():
        images = calibration_scans(teacher, payload, prompts, domain, how, int(steps), seed)
    cache.mkdir(parents=True, exist_ok=True)
    np.save(path, images)
    return images


def measure(args) -> dict:
    from omnilidar.generator.checkpoint import load_generator
    from omnilidar.generator.data import load_range_image, read_domains_index
    from omnilidar.generator.text import load_prompt_cache
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.generation import CALIBRATION_RULES, REFERENCE_SCANS, sample_images, set_features

    calibrated = dict(c.split("=", 1) for c in args.calibrated)
    checked = {label: json.loads(Path(p).read_text()) for label, p in (c.split("=", 1) for c in args.checked)}
    if set(calibrated) != set(checked):
        raise SystemExit(f"--calibrated {sorted(calibrated)} and --checked {sorted(checked)} name different candidates")
    students = {label: load_generator(path, "cpu") for label, path in calibrated.items()}
    payload = next(iter(students.values()))[1]
    seeds = {int(p["seed"]) for _, p in students.values()}
    if len(seeds) > 1:
        raise SystemExit(f"the calibrated students come from different distillation seeds {sorted(seeds)}")
    check = next(iter(checked.values()))["student_check"]
    targets = {m: label_of(check["metrics"][m]["teacher_best"]) for m in check["decided_by"]}
    teacher, _ = load_generator(args.teacher, "cpu")
    spec, prompts = range_image_spec(payload["config"]), load_prompt_cache(args.prompts)
    training, heldout = read_domains_index(args.training), read_domains_index(args.heldout)
    out = {"distillation_seed": seeds.pop(), "candidates": list(calibrated), "targets": targets,
           "check_scans": args.check_scans, "student_scans": args.student_scans, "seed": args.seed,
           "held": {label: {d: held_both(doc, d) for d in payload["domains"]} for label, doc in checked.items()},
           "reference_scans": {where: {} for where in WHERE}, "rules": {r: {} for r in RULES}}
    for domain in payload["domains"]:
        references = {"training": training[domain]["files"][:REFERENCE_SCANS],
                      "held-out unused": heldout[domain]["files"][args.check_scans:]}
        teachers = {label: teacher_scans(teacher, payload, prompts, domain, label, Path(args.cache))
                    for label in {*calibrated, *targets.values()}}
        drawn = {label: sample_images(net, p, prompts, domain, args.student_scans, p["student"]["sampler"],
                                      int(p["student"]["steps"]), args.seed)[0] for label, (net, p) in students.items()}
        for where, files in references.items():
            if not files:
                raise SystemExit(f"{args.heldout}: {domain} has no scans beyond the check's first {args.check_scans}")
            real_images = np.stack([load_range_image(f, spec.shape) for f in files])
            out["reference_scans"][where][domain] = len(files)
            for rule, name in (("closest", "closest"), ("first_holding", "first holding")):
                pick, scores = CALIBRATION_RULES[rule]({c: teachers[c] for c in calibrated}, real_images, spec)
                out["rules"][f"{name}, {where}"][domain] = {"pick": pick, "scores": scores}
            real = set_features(real_images, spec, {}, 8)
            teacher_stats = {label: group_stats(real, images, spec) for label, images in teachers.items()}
            excess = {c: mirrored_excess(group_stats(real, drawn[c], spec), teacher_stats, targets) for c in calibrated}
            out["rules"][f"check mirrored, {where}"][domain] = {"pick": min(excess, key=excess.get), "scores": excess}
        print(domain + ": " + "; ".join(f"{r} -> {out['rules'][r][domain]['pick']}" for r in RULES), flush=True)
    return out


def rows_of(run: dict) -> dict[str, dict[str, str]]:
    """{row: {domain: the candidate it calibrates on}}: each candidate everywhere, then each rule."""
    domains = list(next(iter(run["held"].values())))
    rows = {f"{c} everywhere": {d: c for d in domains} for c in run["candidates"]}
    rows.update({r: {d: v["pick"] for d, v in picks.items()} for r, picks in run["rules"].items()})
    return rows


def summary(run: dict) -> list[str]:
    """Per rule and per candidate everywhere: in how many domains its picks held both checks, and where not."""
    domains, rows, lines = list(next(iter(run["held"].values()))), rows_of(run), []
    for name, picks in rows.items():
        missed = [d for d in domains if not run["held"][picks[d]][d]]
        lines.append(f"{name}: both checks held in {len(domains) - len(missed)}/{len(domains)} domains"
                     + "".join(f"; misses {d} (calibrated on {picks[d]})" for d in missed))
    return lines


def plot(runs: dict[str, dict], path: str) -> None:
    """One panel per run: rows the rules and each candidate everywhere, columns the domains; a cell
    names the candidate and is green where that student held both checks in the domain."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(runs), 1, figsize=(11, 2.4 * len(runs) + 0.6), squeeze=False)
    for ax, (title, run) in zip(axes[:, 0], runs.items()):
        domains = list(next(iter(run["held"].values())))
        rows = rows_of(run)
        grid = np.array([[run["held"][row[d]][d] for d in domains] for row in rows.values()], float)
        ax.imshow(grid, cmap="RdYlGn", vmin=-0.3, vmax=1.3, aspect="auto")
        for i, row in enumerate(rows.values()):
            for j, d in enumerate(domains):
                ax.text(j, i, row[d].split(":")[0], ha="center", va="center", fontsize=7)
        ax.set_xticks(range(len(domains)), domains, fontsize=8)
        ax.set_yticks(range(len(rows)), list(rows), fontsize=8)
        ax.set_title(f"{title}: the candidate each row calibrates on; green where both checks held", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--teacher")
    parser.add_argument("--prompts")
    parser.add_argument("--training", help="the built domains' index (training scans)")
    parser.add_argument("--heldout", help="the held-out domains' index")
    parser.add_argument("--calibrated", action="append", default=[], help="LABEL=student calibrated on LABEL everywhere")
    parser.add_argument("--checked", action="append", default=[], help="LABEL=that student's sampler-tradeoff result")
    parser.add_argument("--check-scans", type=int, default=8, help="held-out scans per domain the check scores against")
    parser.add_argument("--student-scans", type=int, default=8)
    parser.add_argument("--seed", type=int, default=1000, help="the students' sampling seed (not the check's)")
    parser.add_argument("--cache", default="benchmarks/.cache/calibration_choice")
    parser.add_argument("--out", help="JSON to write")
    parser.add_argument("--plot", action="append", default=[], help="TITLE=JSON of an earlier run, to draw")
    parser.add_argument("--figure", help="PNG to draw the runs into")
    args = parser.parse_args(argv)
    runs = {t: json.loads(Path(p).read_text()) for t, p in (x.split("=", 1) for x in args.plot)}
    if args.calibrated:
        import torch

        torch.set_num_threads(1)
        run = measure(args)
        if args.out:
            Path(args.out).write_text(json.dumps(run, indent=1))
        runs[f"distillation seed {run['distillation_seed']}"] = run
    for title, run in runs.items():
        print(f"{title}:\n  " + "\n  ".join(summary(run)))
    if args.figure and runs:
        plot(runs, args.figure)


if __name__ == "__main__":
    main()
