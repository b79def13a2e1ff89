"""omnilidar train-segmentor: one downstream run (supervised-only or GDA) from scratch."""

from __future__ import annotations

from omnilidar.commands._common import seed_arg, segment_arg, settings_arg, threads_arg

HELP = "train MinkUNet or SPVCNN from scratch on a real label subset, plus pseudo-labelled generated scans for GDA"
DATA_FILES = ("workflow/schemas/downstream.schema.yaml",)  # run time reads (omnilidar.provenance)


def add_arguments(parser) -> None:
    settings_arg(parser)
    seed_arg(parser)
    parser.add_argument("--backbone", required=True, choices=["minkunet", "spvcnn"])
    parser.add_argument("--subset", required=True, help="real label subset (make-subset JSON)")
    parser.add_argument("--samples", nargs="*", default=[], help="generated sample shards (GDA)")
    parser.add_argument("--pseudo-labels", nargs="*", default=[], help="their pseudo-label shards, same order")
    parser.add_argument("--domains", nargs="*", default=[], help="names of the generated domains (recorded)")
    parser.add_argument("--max-generated", type=int, default=None, metavar="N",
                        help="use only the first N generated scans: shards in the order given, scans in name "
                             "order (empty scans count but are not trained on); default all")
    parser.add_argument("--pool", help="further real scans (make-subset --exclude) in place of generated ones: "
                                       "with their true labels, or with --pool-labels")
    parser.add_argument("--pool-labels", help="the labeler's labels of the pool (pseudo-label --pool)")
    parser.add_argument("--max-pool", type=int, default=None, metavar="N",
                        help="use only the first N scans of the pool (default all)")
    parser.add_argument("--pool-source", choices=["real", "simulated", "round_trip"], default="real",
                        help="simulated: the pool is real scans run through a domain's scene (simulate-pool); "
                             "round_trip: through a domain's range image and back (round-trip-pool), with their "
                             "carried labels or with --pool-labels")
    parser.add_argument("--lasermix", action="store_true",
                        help="LaserMix each pool scan (with --pool-labels) with a real labelled scan")
    parser.add_argument("--work-dir", default="work/segmentation", help="resumable training state (undeclared)")
    threads_arg(parser)
    parser.add_argument("--out", required=True, help="segmentor checkpoint (weights-only loadable)")
    segment_arg(parser)


def run(args) -> int:
    from omnilidar.config import validate
    from omnilidar.downstream.seg.dataset import records_from_entries
    from omnilidar.downstream.seg.label_spaces import get_label_space
    from omnilidar.downstream.seg.pseudo_label import generated_records, pool_records
    from omnilidar.data.subsets import read_subset
    from omnilidar.devices import set_threads
    from omnilidar.downstream.seg.training import train_segmentor
    from omnilidar.errors import InputError

    set_threads(args.threads)
    settings = validate(dict(args.settings), "downstream.schema.yaml", source="--settings")
    subset = read_subset(args.subset)
    dataset = subset["dataset"]
    real = records_from_entries(subset["entries"], dataset)
    if args.max_generated is not None and not args.samples:
        raise InputError(None, "--max-generated needs generated --samples")
    if args.pool and args.samples:
        raise InputError(args.pool, "give --pool or generated --samples, not both")
    if (args.pool_labels or args.lasermix or args.max_pool is not None) and not args.pool:
        raise InputError(None, "--pool-labels, --lasermix and --max-pool need --pool")
    if args.lasermix and not args.pool_labels:
        raise InputError(args.pool, "--lasermix mixes in the pool unlabelled: give --pool-labels (the labeler's)")
    if args.pool:
        generated, empty = pool_records(args.pool, args.pool_labels), 0
        if args.max_pool is not None:
            if not 1 <= args.max_pool <= len(generated):
                raise InputError(args.pool, f"holds {len(generated)} scans; --max-pool {args.max_pool} is not in "
                                            f"1..{len(generated)}")
            generated = generated[: args.max_pool]
        if generated[0]["format"] != dataset:  # records carry their dataset's scan format
            raise InputError(args.pool, f"pool and subset {args.subset} come from different datasets")
        role = "lasermix" if args.lasermix else "real_pseudo" if args.pool_labels else "real_truth"
        if args.pool_source == "simulated":
            if args.pool_labels or args.lasermix:
                raise InputError(args.pool, "a simulated pool trains on its carried labels (no --pool-labels, --lasermix)")
            role = "simulated"
        if args.pool_source == "round_trip":
            if args.lasermix:
                raise InputError(args.pool, "a round-trip pool is not LaserMix-ed")
            role = "round_trip_pseudo" if args.pool_labels else "round_trip_truth"
    else:
        generated, empty = generated_records(args.samples, args.pseudo_labels, limit=args.max_generated)
        if args.samples and not generated:
            raise InputError(args.samples[0], "the generated scans used hold no non-empty scan")
        if empty:
            print(f"note: {empty} generated scans have no points and are not trained on", flush=True)
        role = "gda" if args.samples else "supervised_only"
    info = {
        "role": role, "pool": args.pool, "pool_labels": args.pool_labels, "max_pool": args.max_pool,
        "dataset": dataset, "percent": 100.0 * subset["fraction"], "subset": args.subset,
        "subset_scans": subset["num_scans"], "domains": list(args.domains), "empty_generated": empty,
        # The generated scans taken (empty ones included); train.num_generated counts those trained on.
        "max_generated": args.max_generated,
        "generated_selection": None if not args.samples else (
            "all scans of the shards" if args.max_generated is None
            else f"first {args.max_generated} scans: shards in the order given, scans in name order"),
    }
    training = {k: settings[k] for k in ("backend", "device", "voxel_size", "max_voxels", "max_points", "models", "schedule",
                                         "augmentation", "mixing")}
    inputs = {"subset": args.subset, "samples": list(args.samples), "pseudo_labels": list(args.pseudo_labels)}
    inputs |= {k: v for k, v in (("pool", args.pool), ("pool_labels", args.pool_labels)) if v}
    summary = train_segmentor(training, args.backbone, real, generated, get_label_space(dataset), args.out,
                              args.work_dir, args.seed, info=info, inputs=inputs,
                              lasermix=args.lasermix, segment=args.segment)
    print(f"{args.backbone} {info['role']}: {summary['num_real']} real + {summary['num_generated']} "
          f"{'pool' if args.pool else 'generated'} scans, "
          f"{summary['iterations']} iterations, {summary['seconds']} s -> {args.out}")
    return 0
