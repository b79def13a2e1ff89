"""How many pixels of a scan are returns, per domain: the generator's training scans, the trained
generator with its own sampler, and distilled students with theirs.

    python benchmarks/measure_student_returns.py --domains data/domains/index.json \
        --prompts data/generator/prompts.pt --generator data/generator/full/model.pt \
        --student data/generator/full/student.pt --scans 8

A pixel is a return when it decodes to a valid range (omnilidar.data.range_image.decode, with the
domain's own sensor geometry), as the sampling stage back-projects it. A missing return is encoded
as -1 and a valid one lies above the encoded minimum range, so a network whose x0 averages over
whether a pixel returns lands in between and, above that minimum, draws a point where the scans it
learnt from have none. The returns fraction of a student against its teacher's shows whether its
few steps blur the sensor's drop-outs. The row range spread (the standard deviation of one row's
returned ranges, averaged over the rows) shows whether they draw the surfaces a beam sees closer
together than their teacher does, and the mean range of the returns whether they draw them nearer.
Prints, per domain, the mean of each over the scans and its spread; every scan has its own sampling
seed, the same for every checkpoint.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import numpy as np
import torch

import bench_record
from omnilidar.data.range_image import decode
from omnilidar.generator.checkpoint import load_generator
from omnilidar.generator.data import load_range_image, read_domains_index
from omnilidar.generator.diffusion import generate
from omnilidar.generator.sampling import domain_points_spec, student_sampling
from omnilidar.generator.schedule import CosineLogSNRSchedule
from omnilidar.generator.text import load_prompt_cache


def returns_fraction(image: np.ndarray, spec) -> float:
    """Fraction of the (2, H, W) image's pixels that decode to a valid range."""
    return float(decode(image, spec)[2].mean())


def row_range_spread(image: np.ndarray, spec) -> float:
    """Mean over the image's rows (those with two returns or more) of the standard deviation of
    their returns' ranges, in metres: how far apart the surfaces one beam sees around the sweep
    are. A network that averages what it cannot tell apart draws them closer together."""
    ranges, _, returns = decode(image, spec)
    spreads = [float(r[m].std()) for r, m in zip(ranges, returns) if m.sum() > 1]
    return statistics.fmean(spreads) if spreads else 0.0


def mean_range(image: np.ndarray, spec) -> float:
    """Mean range of the image's returns, in metres: a network that pulls the ranges it cannot place
    towards their mean draws far surfaces nearer (``range_calibration`` maps them back)."""
    ranges, _, returns = decode(image, spec)
    return float(ranges[returns].mean()) if returns.any() else 0.0


def scan_measures(image: np.ndarray, spec) -> dict[str, float]:
    return {"returns": returns_fraction(image, spec), "row_range_spread_m": row_range_spread(image, spec),
            "mean_range_m": mean_range(image, spec)}


def sampled_measures(den, payload: dict, path: Path, cache: dict, domain: str, seeds: list[int],
                     batch: int) -> tuple[str, list[dict]]:
    """(sampler label, :func:`scan_measures` of each seed's scan) of one loaded checkpoint with its
    own sampler (a student's DDIM steps, the generator's configured sampler)."""
    cfg = payload["config"]
    sampling = student_sampling(cfg["sampling"], payload, path)
    spec = domain_points_spec(cfg, payload, domain)
    schedule = CosineLogSNRSchedule(cfg["diffusion"]["logsnr_min"], cfg["diffusion"]["logsnr_max"])
    entry = cache["domains"][domain]
    fractions = []
    with torch.no_grad():
        for i in range(0, len(seeds), batch):
            images = generate(den, payload["domains"].index(domain), entry["tokens"][0], entry["mask"][0],
                              seeds[i:i + batch], spec.shape, sampler=sampling["sampler"], steps=int(sampling["steps"]),
                              schedule=schedule)
            fractions += [scan_measures(image, spec) for image in images.numpy()]
    kind = "student" if payload.get("student") else "generator"
    return f"{kind} {sampling['sampler']} x {sampling['steps']}", fractions


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--domains", type=Path, required=True, help="the domains index the generator trained on")
    ap.add_argument("--prompts", type=Path, required=True)
    ap.add_argument("--generator", type=Path, required=True, help="the trained generator (the teacher)")
    ap.add_argument("--student", type=Path, action="append", default=[], help="a distilled student (repeatable)")
    ap.add_argument("--only", nargs="*", default=None, help="domains to measure (default: the generator's)")
    ap.add_argument("--scans", type=int, default=8, help="sampled scans per domain and checkpoint")
    ap.add_argument("--seed", type=int, default=1000, help="the first scan's sampling seed")
    ap.add_argument("--batch", type=int, default=8)
    bench_record.out_arg(ap)
    args = ap.parse_args()

    checkpoints = [(path, *load_generator(path)) for path in [args.generator, *args.student]]
    payload = checkpoints[0][2]
    cfg = payload["config"]
    shape = (cfg["range_image"]["height"], cfg["range_image"]["width"])
    index = read_domains_index(args.domains)
    cache = load_prompt_cache(args.prompts)
    seeds = list(range(args.seed, args.seed + args.scans))
    rows, figures = [], {}
    for domain in args.only or payload["domains"]:
        spec = domain_points_spec(cfg, payload, domain)
        measured = {"training scans": [scan_measures(load_range_image(f, shape), spec) for f in index[domain]["files"]]}
        for path, den, own in checkpoints:
            label, scans = sampled_measures(den, own, path, cache, domain, seeds, args.batch)
            measured[f"{label} ({path})" if label in measured else label] = scans
        figures[domain] = {label: {key: [scan[key] for scan in scans] for key in scans[0]}
                           for label, scans in measured.items()}
        for label, values in figures[domain].items():
            returns, spread, far = values["returns"], values["row_range_spread_m"], values["mean_range_m"]
            row = {"what": f"{domain}: {label}",
                   "returns": f"{statistics.fmean(returns):.3f} +- {statistics.stdev(returns):.3f} ({len(returns)} scans)",
                   "row range spread": f"{statistics.fmean(spread):.2f} +- {statistics.stdev(spread):.2f} m",
                   "mean range": f"{statistics.fmean(far):.2f} +- {statistics.stdev(far):.2f} m"}
            print(f"{domain:>10} {label:>40}: returns {row['returns']}, row range spread {row['row range spread']}, "
                  f"mean range {row['mean range']}")
            rows.append(row)
    bench_record.write(args.out, rows, figures, columns=["what", "returns", "row range spread", "mean range"])


if __name__ == "__main__":
    main()
