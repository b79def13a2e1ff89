"""omnilidar export: generated scans with their pseudo-labels or pseudo-boxes in OpenPCDet / mmdet3d layouts."""

from __future__ import annotations

HELP = "export sample shards with their pseudo-labels / pseudo-boxes for OpenPCDet or mmdet3d"
FORMATS = ("openpcdet", "mmdet3d-seg", "mmdet3d-det")
EXPORT_RECORD = "export.json"


def add_arguments(parser) -> None:
    parser.add_argument("--samples", nargs="+", required=True, help="sample shard directories (omnilidar sample)")
    parser.add_argument("--labels", nargs="+", default=None,
                        help="pseudo-label shards, one per sample shard in the same order (mmdet3d-seg)")
    parser.add_argument("--boxes", nargs="+", default=None,
                        help="pseudo-box shards, one per sample shard in the same order (openpcdet, mmdet3d-det)")
    parser.add_argument("--format", required=True, choices=FORMATS, help="target layout")
    parser.add_argument("--val-every", type=int, default=0,
                        help="put the first exported scan and every k-th after it in the val split (0: all train)")
    parser.add_argument("--shift-coor", type=float, nargs=3, default=[0.0, 0.0, 0.0], metavar=("X", "Y", "Z"),
                        help="added to points and box centres (OpenPCDet's SHIFT_COOR, e.g. the platform's "
                             "downstream.det shift so that the ground sits near -1.7 m); default 0 0 0")
    parser.add_argument("--rename-class", action="append", metavar="OLD=NEW",
                        help="write class OLD as NEW, e.g. Car=Vehicle for OpenPCDet's custom configs (repeatable)")
    parser.add_argument("--out", required=True, help="export directory (appears only when complete)")


def _check_inputs(args) -> None:
    from omnilidar.errors import InputError

    needs = {"openpcdet": "boxes", "mmdet3d-seg": "labels", "mmdet3d-det": "boxes"}[args.format]
    unused = "labels" if needs == "boxes" else "boxes"
    if not getattr(args, needs):
        raise InputError(None, f"--format {args.format} needs --{needs} "
                               f"({'pseudo-box' if needs == 'boxes' else 'pseudo-label'} shards)")
    if getattr(args, unused):
        raise InputError(None, f"--format {args.format} does not use --{unused}")


def _check_out(out) -> None:
    """Refuse to replace a directory that is not an earlier export."""
    from omnilidar.errors import InputError

    if out.exists() and not (out.is_dir() and (out / EXPORT_RECORD).is_file()):
        raise InputError(out, f"exists and is not an earlier export (no {EXPORT_RECORD}); choose a new --out")


def run(args) -> int:
    import json
    import time
    from pathlib import Path

    from omnilidar.io.atomic import atomic_path
    from omnilidar.io.export import frames as export_frames

    started = time.time()
    _check_inputs(args)
    out = Path(args.out)
    _check_out(out)
    renames = export_frames.parse_renames(args.rename_class)
    frames = export_frames.collect_frames(args.samples, args.labels, args.boxes)
    planned, empty = export_frames.plan_export(frames, args.val_every, args.shift_coor, renames)
    if args.format == "openpcdet":
        from omnilidar.io.export import openpcdet as writer
    elif args.format == "mmdet3d-seg":
        from omnilidar.io.export import mmdet3d_seg as writer
    else:
        from omnilidar.io.export import mmdet3d_det as writer
    with atomic_path(out) as tmp:
        tmp.mkdir(parents=True)
        summary = writer.write(tmp, planned)
        record = {
            "format": args.format, "splits": summary, "val_every": args.val_every, "shift_coor": list(args.shift_coor),
            "renamed_classes": dict(renames),
            "frames": [{"id": f.name, "split": f.split, "points": str(f.source.points),
                        **({"labels": str(f.source.labels)} if f.source.labels else {}),
                        **({"boxes": len(f.source.boxes)} if f.source.boxes is not None else {})} for f in planned],
            "empty_scans_left_out": [str(f.points) for f in empty],
            "sources": {"samples": args.samples, "labels": args.labels, "boxes": args.boxes},
            "seconds": round(time.time() - started, 2),
        }
        (tmp / EXPORT_RECORD).write_text(json.dumps(record, indent=1))
    counts = ", ".join(f"{s} {v['frames']}" for s, v in summary.items() if s in ("train", "val"))
    print(f"{args.format}: {len(planned)} scans ({counts}), {len(empty)} empty scans left out -> {out}")
    database = summary.get("gt_database", {})
    if database:
        print("box database (train boxes per class): " + ", ".join(f"{k} {v}" for k, v in database.items()))
    for name in [k for k, v in database.items() if v == 0]:
        # OpenPCDet's DataBaseSampler stacks an empty list and fails for a sample group without entries
        print(f"note: no train box of class {name}: leave it out of the box sampling's sample groups")
    return 0
