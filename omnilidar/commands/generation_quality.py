"""omnilidar generation-quality: the multi-domain table (OmniLiDAR vs single-domain baselines)."""

from __future__ import annotations

from omnilidar.commands._common import data_source_arg, report_outputs_arg, seed_arg, settings_arg
from omnilidar.metrics.sample_sets import sample_set_arg

HELP = "score generated scans of every domain (full model vs single-domain baselines) with JSD/MMD/FRD/FRID/FSVD/FPVD"
DATA_FILES = ("workflow/schemas/evaluation.schema.yaml",)  # run time reads (omnilidar.provenance)

FULL = "OmniLiDAR"
BASELINE = "single-domain (R2DM)"


def add_arguments(parser) -> None:
    settings_arg(parser)
    data_source_arg(parser)
    seed_arg(parser)
    parser.add_argument("--domains", required=True, help="domains index JSON (the real scans of each domain)")
    parser.add_argument("--prompts", required=True, help="prompt cache from encode-prompts")
    parser.add_argument("--full", required=True, help="full OmniLiDAR generator checkpoint")
    parser.add_argument("--baseline", action="append", default=[], metavar="DOMAIN=CKPT",
                        help="single-domain baseline checkpoint of one domain (repeat per domain)")
    parser.add_argument("--weights", action="append", default=[], metavar="KIND=PATH",
                        help="extractor weights (official file or self-trained checkpoint), e.g. frd=data/extractors/frd.pt")
    sample_set_arg(parser)  # sets full/DOMAIN and baseline/DOMAIN
    report_outputs_arg(parser)


def run(args) -> int:
    import time

    from omnilidar.config import validate
    from omnilidar.generator.text import load_prompt_cache
    from omnilidar.devices import resolve_device
    from omnilidar.generator.checkpoint import load_generator
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.extractors.weights import load_extractors, parse_pairs
    from omnilidar.metrics.generation import compare, real_domain_images, sample_images, set_features
    from omnilidar.metrics.sample_sets import generated_set, parse_sample_sets
    from omnilidar.progress import ProgressLog
    from omnilidar.provenance import envelope
    from omnilidar.report.generation import (collect_weights, metric_table, provenance_note, samples_figure,
                                             write_outputs)

    settings = validate(dict(args.settings), "evaluation.schema.yaml", source="--settings")
    metrics = settings["generation_quality"]["metrics"]
    n, bs = settings["scans_per_set"], settings["batch_size"]
    extractors = load_extractors(parse_pairs(args.weights, "--weights"), metrics)
    baselines = parse_pairs(args.baseline, "--baseline")
    cache = load_prompt_cache(args.prompts)
    sets = parse_sample_sets(args.samples)
    device = resolve_device(settings["device"], "evaluation.device")
    full, payload = load_generator(args.full, device)
    spec = range_image_spec(payload["config"])
    timings, scores, shown = {}, {}, {"Real": {}, FULL: {}, BASELINE: {}}
    t_all = time.perf_counter()
    progress = ProgressLog(len(payload["domains"]), "domains scored", every_s=0)
    for domain in payload["domains"]:
        t0 = time.perf_counter()
        real_imgs = real_domain_images(args.domains, domain, spec.shape, n)
        real = set_features(real_imgs, spec, extractors, bs, f"real {domain}")
        gen, sec = generated_set(sets, f"full/{domain}", full, payload, cache, domain, n, settings["sampler"],
                                 settings["steps"], args.seed, bs)
        scores[domain] = {FULL: compare(real, set_features(gen, spec, extractors, bs), extractors)}
        scores[domain][FULL]["seconds_per_scan"] = sec
        shown["Real"][domain], shown[FULL][domain] = real_imgs[0], gen[0]
        if domain in baselines:
            base, base_payload = load_generator(baselines[domain], device)
            bgen, bsec = generated_set(sets, f"baseline/{domain}", base, base_payload, cache, domain, n,
                                       settings["sampler"], settings["steps"], args.seed, bs)
            scores[domain][BASELINE] = compare(real, set_features(bgen, spec, extractors, bs), extractors)
            scores[domain][BASELINE]["seconds_per_scan"] = bsec
            shown[BASELINE][domain] = bgen[0]
        timings[domain] = time.perf_counter() - t0
        print(f"{domain}: " + ", ".join(f"{m} {scores[domain][FULL].get(m)}" for m in metrics), flush=True)
        progress.step()
    timings["total"] = time.perf_counter() - t_all
    methods = [m for m in (BASELINE, FULL) if any(m in s for s in scores.values())]
    weights, comparable = collect_weights(scores)
    md = "\n\n".join([
        f"Generation quality per domain ({n} real and {n} generated scans per domain, sampler "
        f"{settings['sampler']} x {settings['steps']} steps; lower is better).",
        metric_table(scores, metrics, methods),
        provenance_note(weights, comparable),
    ])
    result = envelope("generation_quality", "generation-quality", settings, {"seed": args.seed}, timings,
                      args.data_source, metrics=metrics, methods=methods,
                      scans_per_set=n, weights=weights, comparable_with_paper=comparable, scores=scores)
    write_outputs(result, args.out, args.markdown, md)
    samples_figure(args.figure, spec, {k: v for k, v in shown.items() if v})
    print(md)
    return 0
