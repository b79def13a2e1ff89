"""omnilidar convert-extractor-weights: LiDM's torchsparse FSVD/FPVD weights -> this package's layout."""

from __future__ import annotations

HELP = "convert LiDM's torchsparse MinkowskiNet (FSVD) / SPVCNN (FPVD) weights to this package's layout"


def add_arguments(parser) -> None:
    parser.add_argument("--kind", required=True, choices=("fsvd", "fpvd"),
                        help="fsvd: MinkowskiNet (LiDM's minkowskinet/model.ckpt); fpvd: SPVCNN (spvcnn/model.ckpt)")
    parser.add_argument("--in", dest="src", required=True, help="torchsparse checkpoint (LiDM or SPVNAS layout)")
    parser.add_argument("--out", required=True, help="converted state dict to write (weights-only loadable .pt)")


def run(args) -> int:
    from omnilidar.interop.lidm import write_converted
    from omnilidar.metrics.extractors.weights import file_sha

    arch = write_converted(args.kind, args.src, args.out)
    print(f"{args.kind}: {args.src} (sha {file_sha(args.src)}) -> {args.out} "
          f"(width {arch['width']}, {arch['num_classes']} classes)")
    return 0
