"""omnilidar distill-generator: progressive distillation of a trained generator (resumable)."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, settings_arg, threads_arg

HELP = "distill a trained generator into a student that samples in a few DDIM steps (resumes from --work-dir)"
DATA_FILES = ("workflow/schemas/generator.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    threads_arg(parser)
    seed_arg(parser)
    parser.add_argument("--teacher", required=True, help="the trained generator (train-generator's --out)")
    parser.add_argument("--domains", required=True, help="domains index JSON the teacher was trained on")
    parser.add_argument("--prompts", required=True, help="prompt cache from encode-prompts")
    parser.add_argument("--work-dir", required=True, help="resumable state (checkpoints, logs); not a declared output")
    parser.add_argument("--out", required=True,
                        help="the student's weights + config (.pt); with --until, the segment's record (.json)")
    parser.add_argument("--until", type=int, default=None,
                        help="distill only up to this iteration and leave the resumable state in --work-dir")
    parser.add_argument("--preset", default=None, help="the teacher's ablation preset (merged into --settings)")


def run(args) -> int:
    from omnilidar.config import validate
    from omnilidar.generator.distill_steps import calibration_samplers, student_steps
    from omnilidar.generator.presets import apply_preset
    from omnilidar.generator.training import train_generator
    from omnilidar.generator.unet import range_image_spec
    from omnilidar.metrics.generation import choose_on_training_scans
    from omnilidar.devices import set_threads

    set_threads(args.threads)
    settings = validate(dict(args.settings), "generator.schema.yaml", source="--settings")
    if args.preset:
        settings = apply_preset(settings, args.preset)
    # Calibration candidates (calibration_sampler as a list): each domain takes one by the
    # distillation's calibration_rule against its training scans; the index is read for that only.
    choose = (choose_on_training_scans(args.domains, range_image_spec(settings),
                                       settings["distillation"].get("calibration_rule") or "closest")
              if len(calibration_samplers(settings["distillation"])) > 1 else None)
    summary = train_generator(settings, args.domains, args.prompts, args.work_dir, args.out, seed=args.seed,
                              until=args.until, teacher=args.teacher, choose_calibration=choose)
    steps = student_steps(settings["distillation"])
    what = f"up to iteration {args.until}" if args.until else f"{summary['iterations']} iterations"
    print(f"distilled {args.teacher} into a {steps}-step student ({what}) -> {args.out}")
    return 0
