"""omnilidar train-generator: train the OmniLiDAR diffusion model (mmengine Runner, resumable)."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, settings_arg, threads_arg

HELP = "train the text-conditioned range-image diffusion generator (resumes from --work-dir)"
DATA_FILES = ("workflow/schemas/generator.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    threads_arg(parser)
    parser.add_argument("--domains", required=True, help="domains index JSON from the domain builder")
    parser.add_argument("--prompts", required=True, help="prompt cache from encode-prompts")
    parser.add_argument("--work-dir", required=True, help="resumable state (checkpoints, logs); not a declared output")
    parser.add_argument("--out", required=True,
                        help="final EMA weights + resolved config (.pt); with --until, the segment's record (.json)")
    parser.add_argument("--until", type=int, default=None,
                        help="train only up to this iteration, leave the resumable state in --work-dir and write a "
                             "segment record to --out (a segment of a chain that fits a partition's time limit)")
    parser.add_argument(
        "--preset",
        default=None,
        help="ablation preset merged into --settings: single_domain, batch_homogeneous, cdts, cdts_cdfm, cdts_dafs, full",
    )


def run(args) -> int:
    from omnilidar.config import validate
    from omnilidar.generator.presets import apply_preset
    from omnilidar.generator.training import train_generator
    from omnilidar.devices import set_threads

    set_threads(args.threads)
    settings = validate(dict(args.settings), "generator.schema.yaml", source="--settings")
    if args.preset:
        settings = apply_preset(settings, args.preset)
    summary = train_generator(settings, args.domains, args.prompts, args.work_dir, args.out, seed=args.seed,
                              until=args.until)
    what = f"segment up to iteration {args.until}" if args.until else f"{summary['iterations']} iterations"
    print(f"trained {what} ({summary['parameters'] / 1e6:.2f} M parameters) -> {args.out}")
    return 0
