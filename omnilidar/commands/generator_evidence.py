"""omnilidar generator-evidence: the trained generator beats an untrained one, and the prompt controls the domain."""

from __future__ import annotations

from omnilidar.commands._common import report_outputs_arg, data_source_arg, seed_arg, settings_arg

HELP = "BEV JSD/MMD of trained vs untrained generator samples and per-domain statistics vs real scans"
DATA_FILES = ("workflow/schemas/evaluation.schema.yaml",)  # run time reads (omnilidar.provenance)

STATS = ("empty_row_fraction", "near_range_fraction", "points_per_scan", "mean_elevation_deg", "mean_range_m")


def add_arguments(parser) -> None:
    settings_arg(parser)
    data_source_arg(parser)
    seed_arg(parser)
    parser.add_argument("--domains", required=True)
    parser.add_argument("--prompts", required=True)
    parser.add_argument("--checkpoint", required=True, help="trained full generator")
    report_outputs_arg(parser)


def untrained_like(payload: dict, seed: int):
    """The same architecture initialised exactly as training initialises it (same seed), untrained."""
    import torch

    from omnilidar.generator.data import rng_for
    from omnilidar.generator.unet import build_denoiser

    init_seed = int(rng_for(seed, 0x1D17).integers(2**63 - 1))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(init_seed)
        model = build_denoiser(payload["config"], payload["text"]["dim"], len(payload["domains"]))
    return model.eval()


def run(args) -> int:
    import time

    from omnilidar.config import validate
    from omnilidar.generator.text import load_prompt_cache
    from omnilidar.devices import resolve_device
    from omnilidar.generator.checkpoint import load_generator
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.generation import across_domain_correlation, compare, domain_statistics, real_domain_images, sample_images, set_features
    from omnilidar.provenance import envelope
    from omnilidar.report.generation import evidence_figure, write_outputs

    settings = validate(dict(args.settings), "evaluation.schema.yaml", source="--settings")
    ev = settings["evidence"]
    n, bs = ev["scans"], settings["batch_size"]
    device = resolve_device(settings["device"], "evaluation.device")
    trained, payload = load_generator(args.checkpoint, device)
    untrained = untrained_like(payload, int(payload.get("seed", args.seed))).to(device)
    spec = range_image_spec(payload["config"])
    cache = load_prompt_cache(args.prompts)
    out, t0 = {}, time.perf_counter()
    for d in payload["domains"]:
        real_imgs = real_domain_images(args.domains, d, spec.shape, n)
        real = set_features(real_imgs, spec, {}, bs)
        entry = {}
        gens = {}
        for name, model in (("trained", trained), ("untrained", untrained)):
            gens[name], sec = sample_images(model, payload, cache, d, n, settings["sampler"], settings["steps"],
                                            args.seed, bs)
            s = compare(real, set_features(gens[name], spec, {}, bs), {})
            entry[name] = {"JSD": s["JSD"], "MMD_1e4": s["MMD_1e4"], "seconds_per_scan": sec, "notes": s["notes"]}
        entry["statistics"] = {"real": domain_statistics(real_imgs, spec, ev["near_range_m"]),
                               "generated": domain_statistics(gens["trained"], spec, ev["near_range_m"])}
        out[d] = entry
        print(f"{d}: JSD trained {entry['trained']['JSD']} untrained {entry['untrained']['JSD']}", flush=True)

    def better(d, key):
        a, b = out[d]["trained"][key], out[d]["untrained"][key]
        return a is not None and (b is None or a < b)

    control = across_domain_correlation({d: e["statistics"]["real"] for d, e in out.items()},
                                        {d: e["statistics"]["generated"] for d, e in out.items()}, STATS)
    summary = {"trained_closer_JSD": sum(better(d, "JSD") for d in out),
               "trained_closer_MMD": sum(better(d, "MMD_1e4") for d in out), "domains": len(out),
               "domain_control_pearson_r": control}
    f = lambda v: "n/a" if v is None else f"{v:.3f}"  # noqa: E731
    lines = ["| domain | JSD trained | JSD untrained | MMD trained | MMD untrained | "
             + " | ".join(f"{s} real / gen" for s in STATS) + " |", "|" + "---|" * (5 + len(STATS))]
    for d, e in out.items():
        st = e["statistics"]
        lines.append(f"| {d} | {f(e['trained']['JSD'])} | {f(e['untrained']['JSD'])} | {f(e['trained']['MMD_1e4'])} | "
                     f"{f(e['untrained']['MMD_1e4'])} | "
                     + " | ".join(f"{f(st['real'][s])} / {f(st['generated'][s])}" for s in STATS) + " |")
    md = "\n".join([
        f"Generator evidence ({n} scans per set, sampler {settings['sampler']} x {settings['steps']}; MMD x1e-4). "
        f"Trained closer to real than untrained: JSD in {summary['trained_closer_JSD']}/{len(out)} domains, "
        f"MMD in {summary['trained_closer_MMD']}/{len(out)}. Domain control (Pearson r across domains, real vs "
        "generated statistic): " + ", ".join(f"{k} {f(v)}" for k, v in control.items()) + ".", "", *lines])
    result = envelope("generator_evidence", "generator-evidence", settings, {"seed": args.seed},
                      {"total": time.perf_counter() - t0}, args.data_source, summary=summary, domains=out)
    write_outputs(result, args.out, args.markdown, md)
    evidence_figure(args.figure, result)
    print(md)
    return 0
