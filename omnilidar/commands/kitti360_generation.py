"""omnilidar kitti360-generation: the KITTI-360 comparison (FRD, FPD, JSD, MMD)."""

from __future__ import annotations

from omnilidar.commands._common import data_source_arg, report_outputs_arg, seed_arg, settings_arg
from omnilidar.metrics.sample_sets import sample_set_arg

HELP = "score Vehicle-domain samples against KITTI-360 scans (full model vs single-domain baseline)"
DATA_FILES = ("workflow/schemas/evaluation.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    data_source_arg(parser)
    seed_arg(parser)
    parser.add_argument("--index", required=True, help="KITTI-360 dataset index JSON")
    parser.add_argument("--prompts", required=True)
    parser.add_argument("--full", required=True, help="full OmniLiDAR checkpoint")
    parser.add_argument("--baseline", default=None, help="single-domain (R2DM-equivalent) checkpoint of the domain")
    parser.add_argument("--weights", action="append", default=[], metavar="KIND=PATH")
    sample_set_arg(parser)  # sets full and baseline
    report_outputs_arg(parser)


def run(args) -> int:
    import time

    from omnilidar.config import validate
    from omnilidar.generator.text import load_prompt_cache
    from omnilidar.devices import resolve_device
    from omnilidar.generator.checkpoint import load_generator
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.extractors.weights import load_extractors, parse_pairs
    from omnilidar.metrics.generation import compare, dataset_images, sample_images, set_features
    from omnilidar.metrics.sample_sets import generated_set, parse_sample_sets
    from omnilidar.provenance import envelope
    from omnilidar.report.generation import (collect_weights, metric_table, provenance_note, samples_figure,
                                             write_outputs)

    settings = validate(dict(args.settings), "evaluation.schema.yaml", source="--settings")
    k = settings["kitti360"]
    metrics, domain = k["metrics"], k["domain"]
    n, bs = settings["scans_per_set"], settings["batch_size"]
    extractors = load_extractors(parse_pairs(args.weights, "--weights"), metrics)
    cache = load_prompt_cache(args.prompts)
    sets = parse_sample_sets(args.samples)
    t0 = time.perf_counter()
    device = resolve_device(settings["device"], "evaluation.device")
    full, payload = load_generator(args.full, device)
    spec = range_image_spec(payload["config"])
    real_imgs = dataset_images(args.index, k["split"], spec, n)
    real = set_features(real_imgs, spec, extractors, bs, "KITTI-360")
    models = {"OmniLiDAR": ("full", full, payload)}
    if args.baseline:
        models = {"single-domain (R2DM)": ("baseline", *load_generator(args.baseline, device)), **models}
    scores, shown = {}, {"KITTI-360": {domain: real_imgs[0]}}
    for name, (key, den, pl) in models.items():
        gen, sec = generated_set(sets, key, den, pl, cache, domain, n, settings["sampler"], settings["steps"],
                                 args.seed, bs)
        scores[name] = compare(real, set_features(gen, spec, extractors, bs), extractors)
        scores[name]["seconds_per_scan"] = sec
        shown[name] = {domain: gen[0]}
    weights, comparable = collect_weights(scores)
    paper = {"R2DM": {"FRD": 179.43, "FPD": 6.99, "JSD": 0.03, "MMD_1e4": 1.41},
             "WeatherGen": {"FRD": 160.20, "FPD": 6.91, "JSD": 0.03, "MMD_1e4": 1.62},
             "OmniLiDAR (paper)": {"FRD": 158.13, "FPD": 6.89, "JSD": 0.03, "MMD_1e4": 1.12}}
    md = "\n\n".join([
        f"KITTI-360 generation ({n} KITTI-360 {k['split']} scans vs {n} generated {domain} scans; lower is better).",
        metric_table({name: {"": s} for name, s in scores.items()}, metrics, [""]),
        provenance_note(weights, comparable),
        "Paper (64x1024, official extractors, 10k scans): "
        + "; ".join(f"{m} " + "/".join(f"{v}" for v in vals.values()) for m, vals in paper.items())
        + " (FRD / FPD / JSD / MMD x1e-4).",
    ])
    result = envelope("kitti360_generation", "kitti360-generation", settings, {"seed": args.seed},
                      {"total": time.perf_counter() - t0}, args.data_source, metrics=metrics,
                      domain=domain, weights=weights, comparable_with_paper=comparable, scores=scores, paper=paper)
    write_outputs(result, args.out, args.markdown, md)
    samples_figure(args.figure, spec, shown)
    print(md)
    return 0
