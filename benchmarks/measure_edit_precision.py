"""How far SDEdited scans move from their sources: the per-point range error a generator leaves.

    python benchmarks/measure_edit_precision.py \
        --set "strength 0.02=data/samples/attempt-true02/Vehicle" \
        --set "strength 0.1=data/samples/attempt-true10/Vehicle"

Each --set is NAME=SAMPLES: a folder holding sample shards made with generator.sampling.strength
< 1 (each with the sources.json sample writes). For every scan, over the pixels that are returns in
both the edit and its source, the error of the encoded log-range (the unit of
sampling.range_noise, so that the two can be read side by side: gda-decomposition's range-noise
curve says how much of it scans can carry before they stop paying), its median relative range
error, and the share of the source's returns the edit lost or added. Prints the median over scans
of each, per set.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import bench_record
from omnilidar.data.range_image import RangeImageSpec, decode
from omnilidar.errors import InputError
from omnilidar.generator.sampling import SOURCES_FILE, read_sources


def edit_errors(samples: Path) -> dict[str, list[float]]:
    """Per scan of every shard under ``samples``: the encoded-range error's std, the median relative
    range error, and the shares of returns lost and added against the source."""
    shards = sorted(p.parent for p in samples.glob(f"**/{SOURCES_FILE}"))
    if not shards:
        raise InputError(samples, f"no {SOURCES_FILE}: not sampled with generator.sampling.strength < 1")
    out = {"encoded_std": [], "relative_median": [], "lost": [], "added": []}
    for shard in shards:
        doc, edits = read_sources(shard)
        spec = RangeImageSpec(**doc["range_image"])
        for _, edit_file, source in edits:
            edit, src = np.load(edit_file)["image"], np.load(source)["image"]
            edit_range, _, edit_hit = decode(edit, spec)
            src_range, _, src_hit = decode(src, spec)
            both = edit_hit & src_hit
            if not both.any():
                continue
            out["encoded_std"].append(float(np.std(edit[0][both] - src[0][both])))
            out["relative_median"].append(float(np.median(np.abs(edit_range[both] - src_range[both]) / src_range[both])))
            out["lost"].append(float((src_hit & ~edit_hit).sum() / max(src_hit.sum(), 1)))
            out["added"].append(float((edit_hit & ~src_hit).sum() / max(src_hit.sum(), 1)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", action="append", required=True, metavar="NAME=SAMPLES")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    rows, figures = [], {}
    for item in args.set:
        name, sep, folder = item.partition("=")
        if not sep or not name or not folder:
            raise SystemExit(f"--set takes NAME=SAMPLES, got {item!r}")
        try:
            errors = edit_errors(Path(folder))
        except InputError as err:  # one clear line naming the file, no traceback
            raise SystemExit(f"error: {err}") from None
        med = {k: float(np.median(v)) for k, v in errors.items()}
        figures[name] = med | {"scans": len(errors["encoded_std"])}
        rows.append({"set": name, "scans": len(errors["encoded_std"]),
                     "encoded log-range error (std)": f"{med['encoded_std']:.4f}",
                     "relative range error (median)": f"{100 * med['relative_median']:.2f} %",
                     "returns lost": f"{100 * med['lost']:.1f} %", "returns added": f"{100 * med['added']:.1f} %"})
        print(" | ".join(str(v) for v in rows[-1].values()))
    bench_record.write(args.out, rows, figures, columns=list(rows[0]))


if __name__ == "__main__":
    main()
