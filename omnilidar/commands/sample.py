"""omnilidar sample: generate one shard of scans for one domain (resumable, atomic)."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, settings_arg, threads_arg

HELP = "sample a shard of range images + SemanticKITTI point clouds for one domain from a trained generator"
DATA_FILES = ("workflow/schemas/generator.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    threads_arg(parser)
    parser.add_argument("--checkpoint", required=True, help="generator weights from train-generator")
    parser.add_argument("--prompts", required=True, help="prompt cache from encode-prompts")
    parser.add_argument("--domains", default=None,
                        help="domains index (build_domain): the training scans that sampling.strength < 1 starts from")
    parser.add_argument("--domain", required=True, help="domain name (as in the domains index)")
    parser.add_argument("--shard", type=int, required=True, help="shard number K: scans K*N .. K*N+N-1")
    parser.add_argument("--scans-per-shard", type=int, default=None, help="N (default: sampling.scans_per_shard)")
    parser.add_argument("--out", required=True, help="shard directory (appears only when complete)")


def run(args) -> int:
    from omnilidar.checkpoints import job_provenance
    from omnilidar.config import validate
    from omnilidar.devices import resolve_device, set_threads
    from omnilidar.generator.sampling import sample_shard, student_sampling
    from omnilidar.generator.text import load_prompt_cache
    from omnilidar.generator.checkpoint import load_generator
    from omnilidar.generator.data import read_domains_index
    from omnilidar.errors import InputError

    set_threads(args.threads)
    settings = validate(dict(args.settings), "generator.schema.yaml", source="--settings")
    sampling = settings["sampling"]
    n = args.scans_per_shard or sampling["scans_per_shard"]
    device = resolve_device(sampling["device"], "generator.sampling.device")
    denoiser, payload = load_generator(args.checkpoint, device=device)
    sampling = student_sampling(sampling, payload, args.checkpoint)
    cache = load_prompt_cache(args.prompts)
    sources = None
    if args.domains and sampling["strength"] < 1.0:
        index = read_domains_index(args.domains)
        if args.domain not in index:
            raise InputError(args.domains, f"no domain {args.domain!r} (it has {', '.join(index)})")
        sources = index[args.domain]["files"]
    # Scans left by an interrupted job are reused only when they came from this very job.
    provenance = job_provenance("sample", {"sampling": sampling, "domain": args.domain, "shard": args.shard,
                                           "scans_per_shard": n}, args.seed,
                                {"checkpoint": args.checkpoint, "prompts": args.prompts,
                                 **({"domains": args.domains} if sources else {})})
    stats = sample_shard(denoiser, payload, cache, args.domain, args.shard, n, sampling, args.seed, args.out,
                         provenance=provenance, sources=sources)
    print(f"{args.domain} shard {args.shard}: {stats['generated']} generated, {stats['skipped']} reused, "
          f"{stats['seconds']:.1f} s -> {args.out}")
    return 0
