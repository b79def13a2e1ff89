"""omnilidar pi3det-summary: Car AP against the label fraction over the Pi3DET targets (one figure)."""

from __future__ import annotations

HELP = "draw Car AP against the real-label fraction (supervised-only, GDA, box labeler) over Pi3DET results"


def add_arguments(parser) -> None:
    parser.add_argument("results", nargs="+", help="pi3det-result JSON files (results/pi3det_*pct.json)")
    parser.add_argument("--metric", default="3d_R11@0.5", choices=["3d_R11@0.5", "3d_R40@0.5"])
    parser.add_argument("--figure", required=True, help="output PNG")


def run(args) -> int:
    import json
    from pathlib import Path

    from omnilidar.errors import InputError
    from omnilidar.report.detection import label_fraction_figure

    docs = []
    for path in args.results:
        try:
            doc = json.loads(Path(path).read_text())
        except (OSError, ValueError) as err:
            raise InputError(path, f"not a readable Pi3DET result ({err})") from None
        if not isinstance(doc, dict) or not {"platform", "label_percent", "runs", "labeler"} <= set(doc):
            raise InputError(path, "not a pi3det-result output (no platform / label_percent / runs / labeler)")
        docs.append(doc)
    label_fraction_figure(docs, args.figure, args.metric)
    for doc in sorted(docs, key=lambda d: (d["platform"], d["label_percent"])):
        cells = [f"{det} {r['supervised_only']['ap']['Car'][args.metric]:.2f} -> {r['gda']['ap']['Car'][args.metric]:.2f}"
                 for det, r in sorted(doc["runs"].items())]
        print(f"{doc['platform']} {doc['label_percent']} %: " + ", ".join(cells))
    print(f"figure: {args.figure}")
    return 0
