"""Result blocks of README and docs, written from result JSON files so that they cannot drift.

A page holds blocks between ``<!-- results:NAME -->`` and ``<!-- /results:NAME -->``; each
block is rendered from ``<results>/NAME.json`` by the function of that name below (``NAME.short``:
the same file, a shorter rendering). ``omnilidar
docs`` rewrites the blocks; ``--check`` fails when a page and its result files disagree.
"""

from __future__ import annotations

import re
from pathlib import Path

from omnilidar.errors import InputError
from omnilidar.io.json_file import read_json
from omnilidar.report.compute_trend import FAR_DECADES
from omnilidar.report.decomposition import curve_words

BLOCK = re.compile(r"(<!-- results:(?P<name>[a-z0-9_]+(?:\.short)?) -->\n)(?P<body>.*?)(<!-- /results:(?P=name) -->)",
                   re.S)


def _pm(mean: float, std: float | None, scale: float = 100.0) -> str:
    return f"{scale * mean:.2f}" + ("" if std is None else f" +- {scale * std:.2f}")


def _seeds(values: list[float]) -> str:
    return ", ".join(f"{100 * v:.2f}" for v in values)


def _labeler_line(doc: dict) -> str:
    lab = doc.get("labeler")
    if not lab:
        return ""
    check = doc.get("labeler_check") or {}
    verdict = ("stronger than every student it labels for" if check.get("compared") and not check.get("warning")
               else check.get("warning") or check.get("note", ""))
    line = (f"Labeler (trained once on 100 % of the real train labels): val mIoU {100 * lab['val_miou']:.2f}, "
            f"car IoU {100 * lab['val_iou'].get('car', 0.0):.1f}; {verdict}.")
    by_labeler = {}  # attempts with a labeler of their own, grouped by that labeler's scores
    for name, own in (doc.get("attempt_labelers") or {}).items():
        by_labeler.setdefault((own["val_miou"], own["val_iou"].get("car", 0.0)), []).append(f"`{name}`")
    for (miou, car), names in by_labeler.items():
        line += f" Own labeler of {', '.join(names)}: val mIoU {100 * miou:.2f}, car IoU {100 * car:.1f}."
    return line


def semkitti_1pct(doc: dict) -> str:
    """Supervised-only against GDA per backbone, every seed."""
    lines = ["| backbone | seeds | supervised only | GDA | gain per seed |", "|---|---|---|---|---|"]
    for backbone, run in doc["runs"].items():
        sup, gda = run["supervised_only"]["across_seeds"], run["gda"]["across_seeds"]
        lines.append(f"| {backbone} | {run['seeds']} | {_pm(sup['miou_mean'], sup['miou_std'])} | "
                     f"{_pm(gda['miou_mean'], gda['miou_std'])} | {_seeds(run['miou_gain_per_seed'])} |")
    return "\n".join(lines + ["", _labeler_line(doc)])


def gda_decomposition(doc: dict) -> str:
    """Each row per backbone (val), the chain's links seed by seed, the regime check."""
    from omnilidar.report.decomposition import CHAIN, LINKS, ROW_LABELS

    studies = doc["backbones"]
    names = list(studies)
    lines = ["| row | " + " | ".join(f"{b} {doc['setup']['evalset']}" for b in names) + " |",
             "|---|" + "---|" * len(names)]
    for row in next(iter(studies.values()))["rows"]:
        cells = [_pm(studies[b]["rows"][row]["miou_mean"], studies[b]["rows"][row]["miou_std"]) for b in names]
        lines.append(f"| {ROW_LABELS[row]} | " + " | ".join(cells) + " |")
    attempts = [a for a in doc.get("attempts") or {} if all(a in studies[b].get("attempts", {}) for b in names)]
    for name in attempts:  # remedies tried on the generated row (experiments.gda_decomposition.attempts)
        cells = [_pm(studies[b]["attempts"][name]["miou_mean"], studies[b]["attempts"][name]["miou_std"]) for b in names]
        lines.append(f"| +N generated, attempt `{name}` | " + " | ".join(cells) + " |")
    lines += ["", "| link (points lost, seed-paired) | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for link in [k for k in CHAIN if all(k in studies[b]["links"] for b in names)] or ["pseudo_labels", "samples"]:
        cells = [_pm(studies[b]["links"][link]["mean"], studies[b]["links"][link]["std"]) for b in names]
        lines.append(f"| {link} ({LINKS[link][0]} - {LINKS[link][1]}) | " + " | ".join(cells) + " |")
    lines.append("")
    for b in names:
        st = studies[b]
        check, gen = st["regime_check"], st["rows"]["generated"]["gain_over_supervised"]
        clears = "clears" if check.get("ceiling_clears_two_std") else "does not clear"
        held = (f"ceiling gain on the held-out sequence {_pm(check['ceiling_gain']['mean'], check['ceiling_gain']['std'])} "
                f"against 2 std {100 * check['two_std']:.2f} ({clears})" if check.get("set") else "no held-out check")
        lines.append(f"- {b} (seeds {', '.join(str(s) for s in st['seeds'])}): GDA against supervised only "
                     f"{_pm(gen['mean'], gen['std'])} points; costliest link {st['costliest_link']}; {held}.")
        for name in attempts:
            diff = st["attempts"][name]["gain_over_generated"]
            lines.append(f"  - attempt `{name}` against the plain generated row: {_pm(diff['mean'], diff['std'])} points "
                         f"(seed by seed {_seeds(diff['per_seed'])}).")
        lines += ["  " + line for line in _strength_lines(st)]
    return "\n".join(lines + ["", _labeler_line(doc)])


def _strength_lines(study: dict) -> list[str]:
    """One backbone's SDEdit strength curves (gain over supervised-only by sampling strength, per
    generator) and how the strength where they stop paying moves with the generator's iterations."""
    lines = []
    for curve in study.get("strength_curves", {}).values():
        gains = ", ".join(f"{sv:g}: {_pm(m, e)}" for sv, m, e in zip(curve["strength"], curve["gain_mean"],
                                                                  curve["gain_std"]))
        cross = curve["crossing_strength"]
        lines.append(f"- generator of {curve['iterations']} iterations{curve_words(curve)}, gain over supervised only by sampling "
                     f"strength: {gains}; " + (f"stops paying at strength {cross:.2g}." if cross is not None
                                              else "no crossing in the measured strengths."))
    noise = study.get("range_noise_curve")
    if noise:
        gains = ", ".join(f"{n:g}: {_pm(m, e)}" for n, m, e in zip(noise["noise_std"], noise["gain_mean"], noise["gain_std"]))
        zero = f"without noise ({noise['zero']['row']}) {_pm(noise['zero']['mean'], noise['zero']['std'])}; " if noise["zero"] else ""
        cross = noise["crossing_noise"]
        lines.append(f"- real scans with their true labels and range noise added, gain over supervised only by the noise's "
                     f"std in encoded log-range: {zero}{gains}; "
                     + (f"stops paying at {cross:.2g}." if cross is not None else "no crossing in the measured noise."))
    trend = study.get("strength_trend")
    if trend and trend["slope_per_decade"] is not None:
        where = (f"it would reach strength 1 (fresh samples paying) near {trend['iterations_at_strength_1']:.3g} "
                 f"generator iterations ({trend['note']})" if trend["iterations_at_strength_1"] else trend["note"])
        lines.append(f"- the crossing moves {trend['slope_per_decade']:+.2g} in strength per decade of generator "
                     f"iterations: {where}.")
    elif trend:
        lines.append(f"- where the curves stop paying cannot be followed across budgets: {trend['note']}.")
    return lines


def strength_short(doc: dict) -> str:
    """README's view of a strength sweep: per backbone, only its curves and their trend."""
    lines = []
    for backbone, study in doc["backbones"].items():
        lines += [f"{backbone} (seeds {', '.join(str(s) for s in study['seeds'])}):", ""] + _strength_lines(study) + [""]
    return "\n".join(lines)


def gda_budget(doc: dict) -> str:
    """Per budget: compute, sample quality, GDA gain; where the trend crosses each level."""
    budgets = doc["budgets"]
    metrics = list(budgets[0]["quality"])
    lines = ["| generator iterations | CPU-minutes | " + " | ".join(metrics) + " | GDA gain over supervised only |",
             "|---|---|" + "---|" * len(metrics) + "---|"]
    for b in budgets:
        q = [f"{b['quality'][m]:.4g}" if b["quality"][m] is not None else "-" for m in metrics]
        gain = b["gain_over_supervised"]
        lines.append(f"| {b['iterations']} | {b['train_cpu_minutes']:.1f} | " + " | ".join(q) + f" | "
                     f"{_pm(gain['mean'], gain['std'])} |")
    ref = doc["reference"]
    generator = [f"{key.replace('_', ' ')} {', '.join(f'`{v}`' for v in doc['setup'][key])}"
                 for key in ("loss_weighting", "prior") if doc["setup"].get(key)]
    said = f"Generator {', '.join(generator)}. " if generator else ""
    lines += ["", said + f"Supervised only {_pm(ref['supervised_only']['miou_mean'], ref['supervised_only']['miou_std'])}; "
                  f"+N real scans with the labeler's labels gain {_pm(ref['real_pseudo_gain']['mean'], ref['real_pseudo_gain']['std'])} "
                  f"(seeds {', '.join(str(s) for s in ref['seeds'])})."]
    for name, cross in doc["trend"]["crossings"].items():
        if cross["first_measured_budget"] is not None:
            where = f"reached at {cross['first_measured_budget']} iterations"
        elif cross.get("trend_cpu_minutes"):
            fit = doc["trend"]["fit"]
            error = f" +- {100 * fit['slope_std_error']:.2f}" if fit.get("slope_std_error") is not None else ""
            where = (f"not reached in the measured range; the trend ({100 * fit['slope_per_decade']:.2f}{error} "
                     f"points per decade of compute) reaches it near {cross['trend_iterations']:.3g} iterations "
                     f"({cross['trend_cpu_minutes']:.3g} CPU-minutes)")
        else:
            where = "not reached; " + cross.get("note", "")
        if cross.get("earliest_cpu_minutes"):
            steepest = doc["trend"]["fit"]["steepest_slope_per_decade"]
            when = (f"beyond 1e{FAR_DECADES} iterations" if cross["earliest_iterations"] > 10 ** FAR_DECADES else
                    f"no earlier than {cross['earliest_iterations']:.3g} iterations "
                    f"({cross['earliest_cpu_minutes']:.3g} CPU-minutes)")
            where += (f"; even the steepest rise the seeds allow ({100 * steepest:.2f} points per decade, slope + 2 "
                      f"standard errors) reaches it {when}")
        lines.append(f"- {name.replace('_', ' ')} level ({100 * cross['level_gain']:.2f}): {where}.")
    return "\n".join(lines)


def _duration(seconds: float) -> str:
    minutes, seconds = divmod(round(seconds), 60)
    return f"{minutes} min {seconds:02d} s"


def _run_line(doc: dict) -> str:
    runs = doc.get("runs", [])
    steps = ""
    if len(runs) > 1:  # built in steps: each earlier target in a run of its own, then the rest
        steps = " in {} runs ({}, then the rest {})".format(
            len(runs), ", ".join(f"`{r['target']}` {_duration(r['elapsed_seconds'])}" if r["target"]
                                 else f"an interrupted run {_duration(r['elapsed_seconds'])}" for r in runs[:-1]),
            _duration(runs[-1]["elapsed_seconds"]))
    return (f"`{doc['target']}` from a clean clone{steps} (commit {doc['commit']}): {_duration(doc['elapsed_seconds'])}, "
            f"{doc['jobs']} jobs, on {doc.get('machine', 'a 2-core CPU machine')}, install excluded")


def run_cost_short(doc: dict) -> str:
    """One line: wall time, jobs and disk of one measured run."""
    return f"{_run_line(doc)}; it leaves {sum(doc['disk_mb'].values()) / 1024:.1f} GB on disk."


def run_cost(doc: dict) -> str:
    """Wall time, jobs and disk of one measured run (benchmarks/run_cost.py), and the jobs' time."""
    disk = doc["disk_mb"]
    lines = [f"{_run_line(doc)}.", "", "| directory | disk (MB) |", "|---|---|"]
    lines += [f"| `{d}/` | {mb:.1f} |" for d, mb in disk.items()]
    lines.append(f"| total | {sum(disk.values()):.0f} |")
    jobs = doc.get("job_seconds")
    if jobs:  # the jobs' own benchmark files: where the time went
        lines += ["", f"The jobs held {jobs['cpu'] / 60:.1f} CPU-minutes ({jobs['wall'] / 60:.1f} job-minutes of wall "
                      f"time):", "",
                  "| jobs (benchmarks/out/...) | count | CPU minutes | wall minutes |", "|---|---|---|---|"]
        by = sorted(jobs["by_folder"].items(), key=lambda kv: -kv[1]["wall"])
        lines += [f"| `{name}` | {g['jobs']} | {g['cpu'] / 60:.1f} | {g['wall'] / 60:.1f} |" for name, g in by]
    ref = doc.get("against_reference")
    if ref:  # the same jobs in an earlier run of the target
        lines += ["", f"The jobs both this run and the run at {ref['commit'] or 'an earlier commit'} have, in wall "
                      f"minutes:", "", f"| jobs | count | this run | at {ref['commit']} | ratio |", "|---|---|---|---|---|"]
        lines += [f"| {name} | {g['jobs']} | {g['wall'] / 60:.1f} | {g['reference_wall'] / 60:.1f} | {g['ratio']:.2f} |"
                  for name, g in ref["groups"].items()]
    return "\n".join(lines)


def sampler_points(doc: dict) -> str:
    """The sampler study's settings side by side (results/tradeoff.json's points)."""
    metrics = doc["metrics"]
    heads = [f"{m} (x 1e-4)" if m == "MMD" else m for m in metrics]  # BEV MMD as papers print it
    lines = ["| sampler | network evaluations | s per scan | " + " | ".join(heads) + " |",
             "|---|---|---|" + "---|" * len(metrics)]
    for p in doc["points"]:
        cells = [f"{p[f'mean_{m}']:.4g} +- {p[f'std_{m}']:.2g}" for m in metrics]
        lines.append(f"| {p['sampler']} | {p['network_evaluations']} | {p['seconds_per_scan']:.3f} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines + ["", f"Domains {', '.join(doc['domains'])}, {reference_phrase(doc)}; mean over "
                                   f"{doc['seeds']['seed_groups']} groups of scans with distinct sampling seeds +- their "
                                   f"spread; {doc['device']}."])


def reference_phrase(doc: dict) -> str:
    """Which real scans a sampler study scored against (results without a reference record predate
    the held-out sets and scored against the generator's training scans)."""
    ref, n = doc.get("reference"), doc.get("real_scans")
    fewer = {d: k for d, k in (doc.get("real_scans_per_domain") or {}).items() if k < n}  # a domain's set ran out
    if fewer:
        n = f"{n} ({', '.join(f'{d} {k}' for d, k in fewer.items())})"
    if ref and ref.get("held_out"):
        return f"scored against {n} held-out real scans per domain ({', '.join(sorted(set(ref['sources'].values())))})"
    return f"scored against {n} of each domain's training scans (the generator's own)"


def _student_lines(doc: dict, teacher_settings: bool = True) -> list[str]:
    """The student against the teacher's best per metric, (the teacher's other settings by the same
    rule,) and its speed, one line each."""
    check, lines = doc["student_check"], []
    for m in check["decided_by"]:
        c = check["metrics"][m]
        best = c["teacher_best"]
        held = [d for d, v in c["per_domain"].items() if v["held"]]
        missed = "; misses " + ", ".join(f"{d} by {x:+.3g}" for d, x in c["missed"].items()) if c["missed"] else ""
        lines.append(f"- {m}: the {check['student_steps']}-step student is within two standard deviations of the "
                     f"teacher's best ({best['sampler']} x {best['steps']}) in {len(held)} of {len(c['per_domain'])} "
                     f"domains{missed}.")
    for setting, row in (doc.get("teacher_settings_check") or {}).items() if teacher_settings else ():
        verdicts = [f"{m} in {v['held']} of {v['of']}"
                    + (" (misses " + ", ".join(f"{d} by {x:+.3g}" for d, x in v["missed"].items()) + ")"
                       if v["missed"] else "") for m, v in row.items()]
        lines.append(f"- The teacher's {setting} by the same rule: {'; '.join(verdicts)}.")
    chosen = (doc.get("student") or {}).get("calibration_sampler")
    sectors = int((doc.get("student") or {}).get("calibration_sectors") or 1)
    per_sector = f", per image row in each of {sectors} azimuth sectors" if sectors > 1 else ""
    if isinstance(chosen, dict):  # calibration candidates: the setting each domain was fitted on
        by = {}
        for domain, setting in chosen.items():
            by.setdefault(setting, []).append(domain)
        rule = (doc.get("student") or {}).get("calibration_rule") or "closest"
        how = {"closest": "", "first_holding": " (each domain's first candidate whose teacher scans hold the best "
                                                "of each metric on its training scans)"}[rule]
        lines.append("- Its returns and ranges calibrated on " + "; ".join(f"{s.replace(':', ' x ')} in {', '.join(d)}"
                                                                           for s, d in by.items()) + per_sector + how + ".")
    elif per_sector:
        lines.append(f"- Its returns and ranges calibrated{per_sector}.")
    if check.get("speedup_over_default"):
        default = check["default_sampler"]
        # Studies before the side-by-side timing took each row's time from its sets' sampling jobs.
        how = ("timed side by side in the study's job" if "set_seconds_per_scan" in doc["points"][0]
               else "each row timed by its own sampling job")
        lines.append(f"- Speed: {check['speedup_over_default']:.1f}x the generator's own sampler in that run "
                     f"({default['sampler']} x {default['steps']}) in seconds per scan ({doc['device']}; {how}).")
    return lines


def student_check(doc: dict) -> str:
    """The sampler study's settings side by side, and the student against the teacher's best."""
    return "\n".join([sampler_points(doc), "", *_student_lines(doc)])


def student_check_short(doc: dict) -> str:
    """The student's row and its check alone (NAME.short): for runs whose teacher rows another
    block of the page already shows."""
    own = {**doc, "points": [p for p in doc["points"] if p["sampler"] == "student"]}
    return "\n".join([sampler_points(own), "", *_student_lines(doc, teacher_settings=False)])


def sampler_grid(doc: dict) -> str:
    """The best training-free sampler per budget of network evaluations, per metric (the full grid of
    results/tradeoff.json), then the recommended setting and the student's check."""
    metrics = doc["metrics"]
    heads = [f"{m} (x 1e-4)" if m == "MMD" else m for m in metrics]
    lines = ["| network evaluations | " + " | ".join(heads) + " |", "|---|" + "---|" * len(metrics)]
    for budget, best in sorted(doc["best_per_budget"].items(), key=lambda kv: int(kv[0])):
        cells = [f"{best[m]['sampler']}: {best[m]['value']:.4g} +- {best[m]['std']:.2g} (of {best[m]['candidates']})"
                 for m in metrics]
        lines.append(f"| {budget} | " + " | ".join(cells) + " |")
    settings = sorted({p["sampler"] for p in doc["points"]})
    lines += ["", f"{len(doc['points'])} settings of {len(settings)} solvers ({', '.join(settings)}); domains "
                  f"{', '.join(doc['domains'])}, {reference_phrase(doc)}; each metric the mean over {doc['seeds']['seed_groups']} groups of "
                  f"scans with distinct sampling seeds +- their spread; {doc['device']}. Recommended "
                  f"({doc['recommend_rule']}): "
              + "; ".join(f"{m} {r['sampler']} x {r['steps']} ({r['seconds_per_scan']:.3g} s per scan)"
                          for m, r in doc["recommended"].items()) + "."]
    if doc.get("student_check"):
        lines += ["", *_student_lines(doc, teacher_settings=False)]
    if doc.get("teacher_settings_check"):  # the grid's settings by the student's rule, one line
        held_all = [setting for setting, row in doc["teacher_settings_check"].items()
                    if all(not v["missed"] for v in row.values())]
        lines.append(f"- Teacher settings within two standard deviations of the best in every domain on "
                     f"{' and '.join(doc['student_check']['decided_by'])}: {', '.join(held_all) or 'none'} "
                     f"(of {len(doc['teacher_settings_check'])}).")
    return "\n".join(lines)


def pi3det_summary(doc: dict) -> str:
    """Every Pi3DET target: Car 3D AP R11 (R40) per detector, supervised-only -> GDA, and the box
    labeler's own val AP with the pseudo-boxes it kept."""
    rows = doc["targets"]
    detectors = list(rows[0]["runs"])

    def ap(scores: dict) -> str:
        car = scores["Car"]
        return f"{car['3d_R11@0.5']:.2f} ({car['3d_R40@0.5']:.2f})"

    lines = ["| platform | % | real frames | " + " | ".join(f"{d} sup -> GDA" for d in detectors)
             + " | box labeler | labeler's Car boxes on generated scans |", "|---|---|---|" + "---|" * (len(detectors) + 2)]
    for r in rows:
        cells = [f"{ap(run['supervised_only'])}{' (= the labeler)' if run['supervised_only_is_labeler'] else ''} -> "
                 f"{ap(run['gda'])}" for run in r["runs"].values()]
        first = next(iter(r["runs"].values()))
        lab = r["labeler"]
        lines.append(f"| {r['platform']} | {r['label_percent']} | {first['real_frames']} | " + " | ".join(cells)
                     + f" | {ap(lab['val_ap'])} | {lab['pseudo_boxes'].get('Car', 0)} on {lab['generated_scans']} |")
    runs = [run for r in rows for run in r["runs"].values()]
    iterations = sorted({run["iterations"] for run in runs})
    generated = sorted({run["generated_frames"] for run in runs})
    gains = [run["gda"]["Car"]["3d_R11@0.5"] - run["supervised_only"]["Car"]["3d_R11@0.5"] for run in runs]
    warnings = sorted({f"{r['platform']}: {r['labeler_warning']}" for r in rows if r.get("labeler_warning")})
    lines += ["", f"Car 3D AP at IoU 0.5, R11 (R40), percent, one seed; runs of {', '.join(map(str, iterations))} "
                  f"iterations; {', '.join(map(str, generated))} generated scans per GDA run. GDA raises Car R11 in "
                  f"{sum(g > 0 for g in gains)} of the {len(gains)} comparisons, lowers it in {sum(g < 0 for g in gains)}, "
                  f"ties in {sum(g == 0 for g in gains)}."]
    lines += [f"- Labeler check, {w}." for w in warnings] or ["- Labeler check: the box labeler is above every "
                                                              "supervised-only detector it labels for, every class."]
    return "\n".join(lines)


def _percent_range(spread: dict) -> str:
    lo, hi = 100 * spread["min"], 100 * spread["max"]
    return f"{lo:.2g}" if f"{lo:.2g}" == f"{hi:.2g}" else f"{lo:.2g}-{hi:.2g}"


def _anchor_text(anchor: dict) -> str:
    """The anchor's numbers of REFERENCE section 4 (omnilidar.domains.fidelity.ANCHORS), in words."""
    parts = []
    if "weather_fraction" in anchor:
        parts.append("weather returns " + " / ".join(f"{100 * a:.0f}-{100 * b:.0f}" for a, b in
                                                     anchor["weather_fraction"].values()) + " %")
    if "ground_lost_fraction" in anchor:
        a, b = anchor["ground_lost_fraction"]["fed_0_1"]
        parts.append(f"{100 * a:.0f}-{100 * b:.0f} % of ground lost when fed 0..1")
    if "clean_scan_deleted_by_noise_floor" in anchor:
        a, b = anchor["clean_scan_deleted_by_noise_floor"]
        parts.append(f"its noise floor deletes {100 * a:.0f}-{100 * b:.0f} % of a clean scan")
    if anchor.get("zero_remission_points_lost") == 1.0:
        parts.append("every zero-remission point lost")
    if "beams_dropped" in anchor:
        parts.append("beams dropped " + " / ".join(str(v) for v in anchor["beams_dropped"].values()))
    seconds = anchor.get("seconds_per_scan")
    if seconds is not None:
        parts.append(f"{seconds if not isinstance(seconds, list) else '-'.join(f'{v:g}' for v in seconds)} s per scan")
    return f"{anchor.get('anchor', '')}: {'; '.join(parts)}" if parts else anchor.get("anchor", "")


def _scan_names(paths: list[str]) -> str:
    return ", ".join("/".join(Path(p).parts[-3:]) for p in paths)


def domain_fidelity(doc: dict) -> str:
    """Per effect, over its severities (light / moderate / heavy): weather returns, lost points (of
    the ground, for wet ground) and seconds per scan, min-max over scans and draws, beside the
    anchor's figures (results/domain_fidelity.json)."""
    lines = ["| effect | severities | weather returns (% of points) | lost (%) | seconds per scan | anchor |",
             "|---|---|---|---|---|---|"]
    for effect, entry in doc["effects"].items():
        sev = entry["severities"]
        lost_key = "ground_lost" if "ground_lost" in next(iter(sev.values())) else "lost"
        added = " / ".join(_percent_range(v["added"]) for v in sev.values())
        lost = " / ".join(_percent_range(v[lost_key]) for v in sev.values())
        seconds = " / ".join(f"{v['seconds_per_scan']:.2g}" for v in sev.values())
        lines.append(f"| {effect.replace('_', ' ')} | {' / '.join(sev)} | {added} | "
                     f"{lost}{' of ground' if lost_key == 'ground_lost' else ''} | {seconds} | "
                     f"{_anchor_text(entry['anchor'])} |")
    ranges = [(e, v["added_range_quantiles"]) for e, entry in doc["effects"].items()
              for v in entry["severities"].values() if v.get("added_range_quantiles")]
    if ranges:
        q = {e: (min(r["q05"] for name, r in ranges if name == e), max(r["q95"] for name, r in ranges if name == e))
             for e, _ in ranges}
        lines += ["", "Weather returns lie at (5-95 % of their ranges, over severities): "
                  + "; ".join(f"{e.replace('_', ' ')} {lo:.1f}-{hi:.1f} m" for e, (lo, hi) in q.items()) + "."]
    lines += ["", f"{len(doc['scans'])} scans x {len(doc['seeds']['draws'])} draws per severity "
                  f"({_scan_names(doc['scans'])}), {doc['device']}."]
    return "\n".join(lines)


def effects_tradeoff(doc: dict) -> str:
    """Per effect and numerical knob: each setting's seconds per scan and error of the effect's
    primary statistic against the highest-fidelity setting, the chosen default in bold
    (results/effects_tradeoff.json)."""
    lines = ["| effect (severity) | knob | setting: ms per scan, error of the primary statistic |", "|---|---|---|"]
    for effect, study in doc["effects"].items():
        knobs: dict[str, list[str]] = {}
        for row in study["rows"]:
            text = f"{row['value']}: {1e3 * row['time_s']:.3g} ms, {row['errors'].get(study['primary_error'], 0):.2g}"
            knobs.setdefault(row["knob"], []).append(f"**{text}**" if row["is_default"] else text)
        for knob, settings in knobs.items():
            lines.append(f"| {effect.replace('_', ' ')} ({study['severity']}) | {knob} | {'; '.join(settings)} |")
    primaries = ", ".join(f"{e.replace('_', ' ')} `{s['primary_error']}`" for e, s in doc["effects"].items())
    lines += ["", f"Primary statistics: {primaries}. On {_scan_names(doc['scans'])}, "
                  f"{len(doc['seeds']['curves'])} seeds per setting, {doc['device']}."]
    return "\n".join(lines)


def benchmark(doc: dict) -> str:
    """One benchmark's table (benchmarks/bench_record.py): its rows, the command and where it ran."""
    m = doc["machine"]
    columns = doc.get("columns", ["what", "median", "target"])
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(str(r.get(c, "")) for c in columns) + " |" for r in doc["rows"]]
    lines += ["", f"`{doc['command']}` (commit {doc['commit']}, " + (f"one {m['gpu']}, " if m.get("gpu") else "")
              + f"{m['cpus']} CPUs, torch {m['torch']}, {doc['created'][:10]})"]
    return "\n".join(lines)


RENDERERS = {"semkitti_1pct": semkitti_1pct, "gda_decomposition": gda_decomposition, "gda_budget": gda_budget,
             "run_cost": run_cost, "run_cost.short": run_cost_short,
             "sampler_quickstart": sampler_points, "pi3det_summary": pi3det_summary,
             "domain_fidelity": domain_fidelity,
             "effects_tradeoff": effects_tradeoff,
             "sampler_grid": sampler_grid}

PREFIXES = {"bench_": benchmark, "student_": student_check, "samplers_": sampler_points, "sampler_grid_": sampler_grid,
            "gda_decomposition_": gda_decomposition,
            "gda_budget_": gda_budget,
            "run_cost_": run_cost}


SHORT = {run_cost: run_cost_short, gda_decomposition: strength_short, student_check: student_check_short}  # NAME.short: the same file, briefly


def render_page(text: str, results: Path, page: str | Path | None = None) -> str:
    """``text`` with every results block rewritten from ``results/<name>.json``."""

    def block(match: re.Match) -> str:
        name = match["name"]
        renderer = RENDERERS.get(name)
        for prefix, by_prefix in PREFIXES.items():  # kept runs and benchmarks: one file each, one renderer
            if renderer is None and name.startswith(prefix):
                renderer = SHORT.get(by_prefix, by_prefix) if name.endswith(".short") else by_prefix
        if renderer is None:
            raise InputError(page, f"unknown results block {name!r} (known: {', '.join(RENDERERS)}, "
                                   f"{', '.join(p + '<name>' for p in PREFIXES)})")
        doc = read_json(Path(results) / f"{name.removesuffix('.short')}.json", f"result file of block {name!r} not found")
        return f"{match.group(1)}{renderer(doc).rstrip()}\n{match.group(4)}"

    return BLOCK.sub(block, text)
