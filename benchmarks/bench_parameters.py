"""The generator's parameters by part, at a config, with each text encoder's token size.

    python benchmarks/bench_parameters.py [--config config/paper.yaml] [--text-dims 768 384]

Builds the denoiser of ``--config`` (resolved with the schema defaults) for the config's eight
domains and counts its trainable parameters: the backbone, the text conditioning (cross-attention
and the pooled-prompt projection, whose size follows the text encoder's token size: 768 for CLIP
ViT-L/14, the paper's, 384 for the embedded MiniLM), CDFM and DAFS. Nothing runs through the
network; the counts do not depend on the machine. The reference column holds the published
counts (REFERENCE.md): the paper's OmniLiDAR and R2DM's EfficientUNet.
"""

from __future__ import annotations

import argparse

import bench_record
from omnilidar.config import load_config
from omnilidar.generator.unet import build_denoiser, parameter_breakdown

PART_NAMES = {"backbone": "backbone", "cross_attention": "cross-attention (text)", "cdfm": "CDFM",
              "dafs": "DAFS", "total": "total"}
REFERENCE = {"backbone": "R2DM's EfficientUNet 31.1 M", "total": "the paper's OmniLiDAR 97.73 M"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="config/paper.yaml")
    ap.add_argument("--text-dims", type=int, nargs="+", default=[768, 384],
                    help="token embedding sizes of the text encoders to count with (CLIP-L 768, MiniLM 384)")
    bench_record.out_arg(ap)
    args = ap.parse_args()

    g = load_config(args.config)["generator"]
    counts = {dim: parameter_breakdown(build_denoiser(g, dim, len(g["prompts"]))) for dim in args.text_dims}
    columns = ["part", *(f"text tokens of {dim}" for dim in args.text_dims), "reference"]
    rows = []
    for part, name in PART_NAMES.items():
        row = {"part": name, "reference": REFERENCE.get(part, "")}
        row.update({f"text tokens of {dim}": f"{counts[dim][part] / 1e6:.2f} M" for dim in args.text_dims})
        rows.append(row)
        print(" | ".join(row[c] for c in columns))
    bench_record.write(args.out, rows, {"config": args.config, "parameters": {str(d): c for d, c in counts.items()}},
                       columns=columns)


if __name__ == "__main__":
    main()
