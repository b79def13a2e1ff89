"""How much the scans of a sampled set differ from each other and how far they lie from real ones,
per domain: the sets a sampler study scored (each setting's sample shards), beside the real set.

    python benchmarks/measure_sample_diversity.py --domains data/domains/index.json \
        --generator data/generator/full/model.pt --only Vehicle Fog Drone --scans 6 \
        --set "teacher ddpm x 32=data/eval_samples/full/ddpm_32" \
        --set "student ddim x 1=data/eval_samples/student/ddim_1"

Each set is a folder with one folder of sample shards per domain (``<set>/<domain>/shard_*``, as
``sample_eval`` writes them); its first ``--scans`` scans are measured, the scans the study scored.
Both measures are squared distances between per-scan normalised BEV histograms, the points of the
protocol's MMD (``omnilidar.metrics.bev``), x 1e4 as MMD is reported:

* between scans: the mean over pairs of distinct scans of the set. A sampler that draws alike
  scans scores a lower one; the real set's shows how much real scans of the domain differ.
* to real: the mean over pairs of one scan of the set and one real scan.

The protocol's kernel is far wider than these distances, so MMD x 1e4 is close to
2 (2 to_real - between (n-1)/n - real between (m-1)/m) for n scans against m real ones: a set
whose scans vary less scores a higher MMD however close each scan lies to the real ones, and a
sampled set's JSD (of the set's summed histogram) rises when its scans cover fewer cells.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import bench_record
from omnilidar.errors import InputError
from omnilidar.generator.checkpoint import load_generator
from omnilidar.generator.unet import range_image_spec
from omnilidar.metrics.bev import MMD_REPORT_SCALE, between_scan_distance, bev_jsd, bev_mmd
from omnilidar.metrics.generation import real_domain_images, set_features
from omnilidar.metrics.sample_sets import load_sample_set


def set_measures(hists, real_hists) -> dict[str, float]:
    """Between-scan and to-real distances (x 1e4), MMD (x 1e4) and JSD of a set's BEV histograms."""
    return {"between_scans": between_scan_distance(hists) * MMD_REPORT_SCALE,
            "to_real": between_scan_distance(hists, real_hists) * MMD_REPORT_SCALE,
            "MMD": bev_mmd(hists, real_hists) * MMD_REPORT_SCALE, "JSD": bev_jsd(hists, real_hists)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--domains", type=Path, required=True, help="the built domains' index (the real sets)")
    ap.add_argument("--generator", type=Path, required=True, help="the trained generator (its range-image geometry)")
    ap.add_argument("--set", action="append", default=[], metavar="LABEL=FOLDER", required=True,
                    help="a sampled set: a folder with <domain>/shard_* sample shards (repeatable)")
    ap.add_argument("--only", nargs="*", default=None, help="domains to measure (default: the generator's)")
    ap.add_argument("--scans", type=int, default=6, help="the first scans of each set (the study's evaluation.tradeoff.scans)")
    ap.add_argument("--real-scans", type=int, default=16, help="real scans per domain (the study's evaluation.scans_per_set)")
    bench_record.out_arg(ap)
    args = ap.parse_args()

    sets = {}
    for pair in args.set:
        label, sep, folder = pair.partition("=")
        if not sep or not label or not folder:
            raise SystemExit(f"--set {pair!r}: expected LABEL=FOLDER")
        sets[label] = Path(folder)
    _, payload = load_generator(args.generator)
    spec = range_image_spec(payload["config"])
    rows, figures = [], {}
    for domain in args.only or payload["domains"]:
        real = set_features(real_domain_images(args.domains, domain, spec.shape, args.real_scans), spec, {}).bev
        measured = {"real": {"between_scans": between_scan_distance(real) * MMD_REPORT_SCALE, "scans": len(real)}}
        for label, folder in sets.items():
            shards = sorted((folder / domain).glob("shard_*"))
            if not shards:
                raise InputError(folder / domain, f"set {label!r}: no sample shards for {domain}")
            images, _ = load_sample_set(shards, args.scans, f"{label}/{domain}")
            measured[label] = {**set_measures(set_features(images, spec, {}).bev, real), "scans": len(images)}
        figures[domain] = measured
        first = measured[next(iter(sets))]["between_scans"]
        for label, m in measured.items():
            row = {"what": f"{domain}: {label}", "scans": str(m["scans"]),
                   "between scans (x 1e-4)": f"{m['between_scans']:.2f} ({m['between_scans'] / first:.2f}x the first set)",
                   "to real (x 1e-4)": f"{m['to_real']:.2f}" if "to_real" in m else "",
                   "MMD (x 1e-4)": f"{m['MMD']:.2f}" if "MMD" in m else "",
                   "JSD": f"{m['JSD']:.4f}" if "JSD" in m else ""}
            print(f"{domain:>10} {label:>24}: " + ", ".join(f"{k} {v}" for k, v in row.items() if k != "what" and v))
            rows.append(row)
    bench_record.write(args.out, rows, figures,
                       columns=["what", "scans", "between scans (x 1e-4)", "to real (x 1e-4)", "MMD (x 1e-4)", "JSD"])


if __name__ == "__main__":
    try:
        main()
    except InputError as err:  # one line naming the file and the problem, no traceback
        raise SystemExit(f"error: {err}") from None
