"""omnilidar pi3det-summary: the Pi3DET targets side by side (one figure, one JSON table)."""

from __future__ import annotations

HELP = ("draw Car AP against the real-label fraction (supervised-only, GDA, box labeler) over Pi3DET results "
        "and write them as one table")


def add_arguments(parser) -> None:
    parser.add_argument("results", nargs="+", help="pi3det-result JSON files (results/pi3det_*pct.json)")
    parser.add_argument("--metric", default="3d_R11@0.5", choices=["3d_R11@0.5", "3d_R40@0.5"])
    parser.add_argument("--figure", required=True, help="output PNG")
    parser.add_argument("--out", help="output JSON: one row per target (what docs/detection.md renders)")


def run(args) -> int:
    import json
    from pathlib import Path

    from omnilidar.downstream.det.experiments import summary_table
    from omnilidar.errors import InputError
    from omnilidar.io.atomic import write_text_atomic
    from omnilidar.report.detection import label_fraction_figure

    docs = []
    for path in args.results:
        try:
            doc = json.loads(Path(path).read_text())
        except (OSError, ValueError) as err:
            raise InputError(path, f"not a readable Pi3DET result ({err})") from None
        if not isinstance(doc, dict) or not {"platform", "label_percent", "runs", "labeler"} <= set(doc):
            raise InputError(path, "not a pi3det-result output (no platform / label_percent / runs / labeler)")
        docs.append(doc | {"_path": str(path)})
    label_fraction_figure(docs, args.figure, args.metric)
    if args.out:
        write_text_atomic(args.out, json.dumps(summary_table(docs), indent=1))
    for doc in sorted(docs, key=lambda d: (d["platform"], d["label_percent"])):
        cells = [f"{det} {r['supervised_only']['ap']['Car'][args.metric]:.2f} -> {r['gda']['ap']['Car'][args.metric]:.2f}"
                 for det, r in sorted(doc["runs"].items())]
        print(f"{doc['platform']} {doc['label_percent']} %: " + ", ".join(cells))
    print(f"figure: {args.figure}" + (f"  table: {args.out}" if args.out else ""))
    return 0
