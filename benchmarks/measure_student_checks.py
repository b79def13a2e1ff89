"""Student checks side by side, domain by domain: how far each student lies from the teacher's
best setting in units of the two standard deviations it is allowed (at most 1: held).

    python benchmarks/measure_student_checks.py --check "per row, seed 1=docs/results/x.json" \
        --check "per sector, seed 1=docs/results/y.json" --out docs/figures/student_checks.png

Each --check is LABEL=PATH of a result of ``omnilidar sampler-tradeoff`` with a student. Prints one
line per check and metric (excess / (2 x spread) per domain) and draws one panel per metric.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def ratios(doc: dict, metric: str) -> dict[str, float]:
    """Per domain: the student's excess over the teacher's best over twice their combined spread."""
    per_domain = doc["student_check"]["metrics"][metric]["per_domain"]
    return {d: v["excess"] / (2 * v["spread"]) for d, v in per_domain.items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="append", required=True, help="LABEL=PATH of a sampler-tradeoff result")
    parser.add_argument("--metrics", nargs="+", default=["JSD", "MMD"])
    parser.add_argument("--out", help="figure to write (PNG)")
    args = parser.parse_args(argv)
    checks = {label: json.loads(Path(path).read_text()) for label, path in (c.split("=", 1) for c in args.check)}
    domains = list(next(iter(checks.values()))["student_check"]["metrics"][args.metrics[0]]["per_domain"])
    for metric in args.metrics:
        for label, doc in checks.items():
            r = ratios(doc, metric)
            held = sum(v <= 1 for v in r.values())
            print(f"{metric} {label}: held {held}/{len(r)}; excess / 2 std: "
                  + ", ".join(f"{d} {r[d]:+.2f}" for d in domains))
    if not args.out:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(args.metrics), figsize=(6 * len(args.metrics), 3.6), squeeze=False)
    width = 0.8 / len(checks)
    for ax, metric in zip(axes[0], args.metrics):
        for k, (label, doc) in enumerate(checks.items()):
            r = ratios(doc, metric)
            ax.bar(np.arange(len(domains)) + (k - (len(checks) - 1) / 2) * width, [r[d] for d in domains], width,
                   label=label)
        ax.axhline(1.0, color="k", lw=1, ls="--")
        ax.set_ylim(bottom=max(ax.get_ylim()[0], -2.0))  # far below the line (Beam32) says nothing more
        ax.set_xticks(range(len(domains)), domains, rotation=30, ha="right")
        ax.set_ylabel(f"{metric}: excess over teacher / (2 std)")
        ax.set_title(f"{metric}: held at or below the dashed line (axis cut at -2)")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(checks), 3), fontsize=8)
    fig.tight_layout(rect=(0, 0.06 * ((len(checks) + 2) // 3), 1, 1))
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
