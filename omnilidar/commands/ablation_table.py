"""omnilidar ablation-table: the paper's six training/architecture configurations."""

from __future__ import annotations

from omnilidar.commands._common import data_source_arg, report_outputs_arg, seed_arg, settings_arg
from omnilidar.metrics.sample_sets import sample_set_arg

HELP = "score the ablation presets (single-domain ... full) averaged over domains"
DATA_FILES = ("workflow/schemas/evaluation.schema.yaml",)  # run time reads (omnilidar.provenance)

LABELS = {
    "single_domain": "single-domain (Vehicle only)",
    "batch_homogeneous": "batch-homogeneous",
    "cdts": "CDTS",
    "cdts_cdfm": "CDTS + CDFM",
    "cdts_dafs": "CDTS + DAFS",
    "full": "CDTS + CDFM + DAFS (OmniLiDAR)",
}


def add_arguments(parser) -> None:
    settings_arg(parser)
    data_source_arg(parser)
    seed_arg(parser)
    parser.add_argument("--domains", required=True)
    parser.add_argument("--prompts", required=True)
    parser.add_argument("--checkpoint", action="append", default=[], metavar="PRESET=CKPT", required=True)
    parser.add_argument("--weights", action="append", default=[], metavar="KIND=PATH")
    sample_set_arg(parser)  # sets PRESET/DOMAIN
    report_outputs_arg(parser)


def run(args) -> int:
    import time

    import numpy as np

    from omnilidar.config import validate
    from omnilidar.generator.text import load_prompt_cache
    from omnilidar.devices import resolve_device
    from omnilidar.generator.checkpoint import load_generator
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.extractors.weights import load_extractors, parse_pairs
    from omnilidar.metrics.generation import compare, real_domain_images, sample_images, set_features
    from omnilidar.metrics.sample_sets import generated_set, parse_sample_sets
    from omnilidar.provenance import envelope
    from omnilidar.report.generation import (collect_weights, metric_table, metric_value, provenance_note,
                                             samples_figure, write_outputs)

    settings = validate(dict(args.settings), "evaluation.schema.yaml", source="--settings")
    metrics = settings["ablation"]["metrics"]
    n, bs = settings["scans_per_set"], settings["batch_size"]
    extractors = load_extractors(parse_pairs(args.weights, "--weights"), metrics)
    ckpts = parse_pairs(args.checkpoint, "--checkpoint")
    presets = [p for p in settings["ablation"]["presets"] if p in ckpts]
    cache = load_prompt_cache(args.prompts)
    sets = parse_sample_sets(args.samples)
    device = resolve_device(settings["device"], "evaluation.device")
    models = {p: load_generator(ckpts[p], device) for p in presets}
    spec = range_image_spec(next(iter(models.values()))[1]["config"])
    domains = next(iter(models.values()))[1]["domains"]
    scores = {p: {} for p in presets}
    shown = {"Real": {}, **{LABELS[p]: {} for p in presets}}
    timings = {}
    for domain in domains:
        t0 = time.perf_counter()
        real_imgs = real_domain_images(args.domains, domain, spec.shape, n)
        real = set_features(real_imgs, spec, extractors, bs, f"real {domain}")
        shown["Real"][domain] = real_imgs[0]
        for p in presets:
            den, payload = models[p]
            gen, sec = generated_set(sets, f"{p}/{domain}", den, payload, cache, domain, n, settings["sampler"],
                                     settings["steps"], args.seed, bs)
            scores[p][domain] = compare(real, set_features(gen, spec, extractors, bs), extractors)
            scores[p][domain]["seconds_per_scan"] = sec
            shown[LABELS[p]][domain] = gen[0]
        timings[domain] = time.perf_counter() - t0
        print(f"{domain} done in {timings[domain]:.0f} s", flush=True)
    # Mean over domains of each metric (MMD averaged in raw units, shown x1e-4).
    means = {}
    for p in presets:
        row = {}
        for m in metrics:
            key = "MMD" if m == "MMD" else m
            vals = [s.get(key) for s in scores[p].values()]
            row[key] = float(np.mean(vals)) if vals and all(v is not None for v in vals) else None
        if row.get("MMD") is not None:
            row["MMD_1e4"] = row["MMD"] * 1e4
        means[p] = row
    table = {LABELS[p]: {"mean": means[p]} for p in presets}
    weights, comparable = collect_weights(scores)
    md = "\n\n".join([
        f"Ablation: mean over {len(domains)} domains ({n} scans per set; lower is better).",
        metric_table(table, metrics, ["mean"]),
        provenance_note(weights, comparable),
    ])
    result = envelope("ablation", "ablation-table", settings, {"seed": args.seed}, timings, args.data_source,
                      metrics=metrics, presets=presets, labels={p: LABELS[p] for p in presets},
                      mean={p: {m: metric_value(means[p], m) for m in metrics} for p in presets},
                      weights=weights, comparable_with_paper=comparable, scores=scores)
    write_outputs(result, args.out, args.markdown, md)
    samples_figure(args.figure, spec, shown)
    print(md)
    return 0
