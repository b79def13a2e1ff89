"""How well trained generators denoise, per noise level, against the domain's mean image.

    python benchmarks/measure_denoising.py --domains data/domains/index.json \
        --prompts data/generator/prompts.pt --generator data/generator/full/model.pt \
        --generator data/generator/attempt-budget1000/model.pt --domain Vehicle

Each of the domain's training scans is noised at diffusion times t (--times) with --noise-seeds
seeded draws; the generator predicts x0 (clamped, as its samplers do) and the error is the mean
squared error over all pixels of both channels. The reference is the domain's mean image, the
best prediction that knows nothing but the domain: where a generator's error is above it (ratio
> 1), it has not yet learned the domain's coarse layout at that noise level, and its samplers,
which decide that layout at high noise, cannot draw it. The mean image is a constant per domain, so
a network that fits its own training scans less well than it at high noise is short of training
(or of loss weight at those levels), not of capacity.
Each channel is measured against its own mean image: the log-range channel is the scan's geometry;
the intensity channel is mostly unpredictable texture, whose error would otherwise swamp it (six
times the range channel's mean-image error on the embedded default's Vehicle scans).
Prints the ratio per generator, channel and time, mean and spread over the noise seeds.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import numpy as np
import torch

import bench_record
from omnilidar.data.range_image import RangeImageSpec, decode, unproject
from omnilidar.generator.checkpoint import load_generator
from omnilidar.generator.data import load_range_image, read_domains_index
from omnilidar.generator.diffusion import generate, noised
from omnilidar.generator.sampling import domain_points_spec
from omnilidar.generator.schedule import CosineLogSNRSchedule, predict_x0
from omnilidar.generator.text import load_prompt_cache

CHANNELS = ("range", "intensity")  # the range image's channels (omnilidar.data.range_image.encode)


def denoising_errors(denoiser, payload: dict, images: torch.Tensor, domain_name: str, tokens, mask,
                     times: list[float], seeds: list[int], batch: int) -> dict[float, list[float]]:
    """{t: [per-channel x0 MSE (C,) per noise seed]} of ``denoiser`` on ``images`` (N, C, H, W)."""
    d = payload["config"]["diffusion"]
    schedule = CosineLogSNRSchedule(d["logsnr_min"], d["logsnr_max"])
    domain = torch.full((images.shape[0],), payload["domains"].index(domain_name), dtype=torch.long)
    out = {}
    with torch.no_grad():
        for t in times:
            times_of_scans = torch.full((len(images),), t, dtype=torch.float32)
            errors = []
            for seed in seeds:
                noise = torch.randn(images.shape, generator=torch.Generator().manual_seed(seed))
                x_t, logsnr = noised(images, times_of_scans, noise, schedule)  # the trainer's noising
                squared = torch.zeros(images.shape[1], dtype=torch.float64)
                for i in range(0, len(images), batch):
                    sl = slice(i, i + batch)
                    n = x_t[sl].shape[0]
                    eps = denoiser(x_t[sl], logsnr[sl], domain[sl], tokens.expand(n, -1, -1), mask.expand(n, -1))
                    squared += (predict_x0(x_t[sl], eps, logsnr[sl]) - images[sl]).double().square().sum(dim=(0, 2, 3))
                errors.append(squared / (images.numel() / images.shape[1]))
            out[t] = errors
    return out


def image_points(image: np.ndarray, spec: RangeImageSpec) -> np.ndarray:
    """(N, 4) points of one (2, H, W) range image in [-1, 1]."""
    ranges, intensity, valid = decode(image, spec)
    return unproject(ranges, intensity, spec, mask=valid)


def sample_points(denoiser, payload: dict, domain_name: str, tokens, mask, seed: int = 0) -> np.ndarray:
    """One scan of ``domain_name`` drawn with the generator's own sampler and steps."""
    cfg = payload["config"]
    spec = domain_points_spec(cfg, payload, domain_name)
    d, s = cfg["diffusion"], cfg["sampling"]
    with torch.no_grad():
        image = generate(denoiser, payload["domains"].index(domain_name), tokens, mask, [seed], spec.shape,
                         s["sampler"], s["steps"], CosineLogSNRSchedule(d["logsnr_min"], d["logsnr_max"]))
    return image_points(image[0].numpy(), spec)


def bev_figure(path: Path, panels: list[tuple[str, np.ndarray]], reach: float = 40.0) -> None:
    """Bird's-eye view of each (title, points) panel within +-``reach`` m, coloured by height."""
    from omnilidar.io.figure import plt, save_figure

    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.6), squeeze=False)
    for ax, (title, pts) in zip(axes[0], panels):
        keep = (np.abs(pts[:, 0]) < reach) & (np.abs(pts[:, 1]) < reach)
        ax.scatter(pts[keep, 0], pts[keep, 1], s=0.05, c=pts[keep, 2], cmap="viridis", vmin=-3, vmax=2)
        ax.set_xlim(-reach, reach), ax.set_ylim(-reach, reach), ax.set_aspect("equal")
        ax.set_title(title, fontsize=7)
        ax.tick_params(labelsize=6)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--domains", required=True, help="data/domains/index.json")
    ap.add_argument("--prompts", required=True, help="data/generator/prompts.pt")
    ap.add_argument("--generator", action="append", required=True, help="trained generator checkpoint (repeat)")
    ap.add_argument("--domain", default="Vehicle")
    ap.add_argument("--times", type=float, nargs="+", default=[0.1, 0.3, 0.5, 0.7, 0.8, 0.9, 0.97])
    ap.add_argument("--noise-seeds", type=int, default=3)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--figure", type=Path, default=None,
                    help="also draw one scan of each generator (its own sampler, seed 0) in bird's-eye view "
                         "beside one of the domain's training scans (PNG)")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    name = args.domain
    if args.threads:
        torch.set_num_threads(args.threads)
    domains = read_domains_index(args.domains)
    if name not in domains:
        raise SystemExit(f"{args.domains}: no domain {name!r} (has {', '.join(domains)})")
    cache = load_prompt_cache(args.prompts)
    entry = cache["domains"][name]
    tokens, mask = entry["tokens"][0].float(), entry["mask"][0].bool()  # the first prompt, as sampling uses
    seeds = list(range(args.noise_seeds))
    rows, figures = [], {"domain": name, "times": args.times, "noise_seeds": seeds, "generators": []}
    images, panels = None, []
    for path in args.generator:
        denoiser, payload = load_generator(path)
        shape = (payload["config"]["range_image"]["height"], payload["config"]["range_image"]["width"])
        if images is None:
            images = torch.from_numpy(np.stack([load_range_image(f, shape) for f in domains[name]["files"]]))
            mean_image = images.mean(dim=0, keepdim=True)
            baseline = (images - mean_image).double().square().mean(dim=(0, 2, 3))
            figures |= {"scans": len(images), "mean_image_mse": dict(zip(CHANNELS, baseline.tolist()))}
            print(f"{name}: {len(images)} training scans; the mean image's MSE "
                  + ", ".join(f"{c} {float(b):.4f}" for c, b in zip(CHANNELS, baseline)))
            spec = domain_points_spec(payload["config"], payload, name)
            panels.append((f"a {name} training scan", image_points(images[0].numpy(), spec)))
        iterations = payload["config"]["training"]["iterations"]
        errors = denoising_errors(denoiser, payload, images, name, tokens, mask, args.times, seeds, args.batch)
        # Checkpoints from before loss_weighting / prior existed were all trained with min-SNR, no prior.
        diffusion = payload["config"]["diffusion"]
        weighting, prior = diffusion.get("loss_weighting", "min_snr"), diffusion.get("prior", "zero")
        record = {"checkpoint": str(path), "iterations": iterations, "loss_weighting": weighting, "prior": prior,
                  "mse": {}, "ratio_to_mean_image": {}}
        for c, channel in enumerate(CHANNELS):
            ratios = {t: [float(e[c] / baseline[c]) for e in errs] for t, errs in errors.items()}
            row = {"generator": Path(path).parent.name, "iterations": str(iterations), "loss weighting": weighting,
                   "prior": prior, "channel": channel}
            for t in args.times:
                spread = statistics.stdev(ratios[t]) if len(seeds) > 1 else 0.0
                row[f"t = {t:g}"] = f"{statistics.mean(ratios[t]):.2f} +- {spread:.2f}"
            rows.append(row)
            record["mse"][channel] = {str(t): [float(e[c]) for e in errs] for t, errs in errors.items()}
            record["ratio_to_mean_image"][channel] = {str(t): r for t, r in ratios.items()}
            print("  ".join(f"{k} {v}" for k, v in row.items()), flush=True)
        figures["generators"].append(record)
        if args.figure:
            panels.append((f"{Path(path).parent.name}: {iterations} it.\n{weighting}, prior {prior}",
                           sample_points(denoiser, payload, name, tokens, mask)))
    if args.figure:
        bev_figure(args.figure, panels)
    bench_record.write(args.out, rows, figures, columns=["generator", "iterations", "loss weighting", "prior", "channel",
                                                         *(f"t = {t:g}" for t in args.times)])


if __name__ == "__main__":
    main()
