"""omnilidar train-labeler: the fixed labeler (imported user checkpoint, or trained once on 100 %)."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, segment_arg, settings_arg, threads_arg

HELP = "make the fixed pseudo-labeler: import downstream.labeler.checkpoint or train it on the full real train split"
DATA_FILES = ("workflow/schemas/downstream.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--index", nargs="?", default=None,
                        help="SemanticKITTI dataset index (its train split trains the labeler; not needed to import)")
    parser.add_argument("--work-dir", default="work/labeler", help="resumable training state (undeclared)")
    threads_arg(parser)
    parser.add_argument("--out", required=True, help="labeler checkpoint (weights-only loadable)")
    segment_arg(parser)


def run(args) -> int:
    from omnilidar.config import validate
    from omnilidar.downstream.seg.label_spaces import get_label_space
    from omnilidar.downstream.seg.labeler import LABEL_SPACE, import_labeler, labeler_records, training_settings
    from omnilidar.devices import set_threads
    from omnilidar.downstream.seg.training import train_segmentor

    set_threads(args.threads)
    section = validate({"labeler": dict(args.settings)}, "downstream.schema.yaml", source="--settings")["labeler"]
    if section["checkpoint"]:
        info = import_labeler(section, section["checkpoint"], args.out)
        print(f"imported labeler {info['source']} ({info['model']['backbone']}) -> {args.out}")
    else:
        if not args.index:
            from omnilidar.errors import InputError

            raise InputError(None, "--index is needed to train the labeler (no downstream.labeler.checkpoint given)")
        real = labeler_records(args.index)
        summary = train_segmentor(training_settings(section), section["backbone"], real, [],
                                  get_label_space(LABEL_SPACE), args.out, args.work_dir, args.seed,
                                  info={"role": "labeler", "train_scans": len(real)},
                                  inputs={"index": args.index}, command="train-labeler", segment=args.segment)
        print(f"trained labeler: {summary['iterations']} iterations, {summary['seconds']} s -> {args.out}")
    return 0
