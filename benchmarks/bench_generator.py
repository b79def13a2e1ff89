"""Generator speed: training step time and sampling time per scan, per sampler and step count.

    python benchmarks/bench_generator.py                 # embedded default config on this machine
    python benchmarks/bench_generator.py --paper --device cuda --batch 16 \
        --samplers ddpm:256 dpmpp_2m:32                  # paper scale on a GPU (the paper: 3.52 s/frame, H100)
    python benchmarks/bench_generator.py --geometries 32x256 64x512 64x512:128 64x1024:128 \
        --samplers dpmpp_2m:20                           # what resolution and azimuth-window training cost
    python benchmarks/bench_generator.py --student data/generator/full/student.pt \
        --samplers dpmpp_2m:20 unipc:8                   # a distilled student beside its teacher's solvers
    python benchmarks/bench_generator.py --levels 2 1 1,2,2,2
                                                         # one network evaluation by UNet level, per
                                                         # residual blocks (one number or one per level)

Prints medians over --repeats runs and the ratio of each sampler setting to the first one;
with several --geometries (HxW, or HxW:C for training on C-column azimuth windows) each
geometry's training step and sampling time, and their ratios to the first geometry. With
--levels, one forward pass (the sampling batch) of each residual-block setting, split by UNet
level into its residual blocks and the rest (attention, CDFM, DAFS, resampling), and each
setting's whole pass as a ratio to the first: where a student's fewer blocks save the most.
Random weights and random prompt tokens: speed does not depend on them. With --student the
trained checkpoints are timed instead: the student in its own DDIM steps and its teacher (the
checkpoint the student names) with each of --samplers, on the Vehicle prompt, one run.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch

import bench_record
from omnilidar.config import section_defaults
from omnilidar.generator.diffusion import generate
from omnilidar.generator.training import make_diffusion_model
from omnilidar.generator.unet import ResBlock, build_denoiser, count_parameters

PAPER = {
    "range_image": {"height": 64, "width": 1024},
    "training": {"crop_width": None},  # the paper trains on whole sweeps
    "model": {"base_channels": 64, "channel_multipliers": [1, 2, 4, 8], "num_res_blocks": 3,
              "cross_attention_levels": [1, 2, 3], "cdfm_levels": [2, 3], "mamba": {"d_state": 16}},
}


def _merge(base, patch):
    for k, v in patch.items():
        if isinstance(v, dict):
            _merge(base[k], v)
        else:
            base[k] = v
    return base


def _settings(args) -> dict:
    """The embedded default's generator settings, at paper scale with --paper."""
    settings = copy.deepcopy(section_defaults("generator"))
    return _merge(settings, PAPER) if args.paper else settings


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--paper", action="store_true", help="paper-scale architecture and 64x1024 images")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--batch", type=int, default=None, help="batch size (default: the config's)")
    ap.add_argument("--train-steps", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--samplers", nargs="*", default=["ddpm:20", "ddim:20", "dpmpp_2m:10", "dpmpp_2m:20", "dpmpp_2m:50"],
                    help="name:steps pairs")
    ap.add_argument("--bf16", action="store_true", help="bf16 autocast (CUDA)")
    ap.add_argument("--geometries", nargs="*", default=[],
                    help="HxW or HxW:CROP image geometries to compare (default: the config's)")
    ap.add_argument("--student", default=None, help="a distilled student checkpoint (distill_generator's output)")
    ap.add_argument("--prompts", default="data/generator/prompts.pt", help="prompt cache, with --student")
    ap.add_argument("--levels", nargs="+", default=None, metavar="BLOCKS",
                    help="residual blocks per level to time one evaluation of, by level: N or N,N,N,N")
    bench_record.out_arg(ap)
    args = ap.parse_args()
    if args.levels:
        bench_record.write(args.out, *bench_levels(args))
        return
    if args.student:
        bench_record.write(args.out, *bench_student(args))
        return
    rows, figures = [], {}
    geometries = args.geometries or [None]
    first = None
    for geometry in geometries:
        result = bench_geometry(args, geometry, rows, figures)
        first = first or result
        if len(geometries) > 1:
            print(f"  {geometry}: train step ratio {result[0] / first[0]:.2f}, "
                  f"sampling ratio {result[1] / first[1]:.2f} (to {geometries[0]})")
    bench_record.write(args.out, rows, figures)


def bench_geometry(args, geometry: str | None, rows: list, figures: dict) -> tuple[float, float]:
    """Time one geometry, adding its table rows and figures; returns (median train step, median
    s/scan of the first sampler)."""

    device = torch.device(args.device)
    settings = _settings(args)
    if geometry:
        size, _, crop = geometry.partition(":")
        height, width = (int(v) for v in size.split("x"))
        settings["range_image"].update(height=height, width=width)
        settings["training"]["crop_width"] = int(crop) if crop else None
    h, w = settings["range_image"]["height"], settings["range_image"]["width"]
    b_train = args.batch or settings["training"]["batch_size"]
    b_sample = args.batch or settings["sampling"]["batch_size"]
    text_dim, n_tok, n_dom = 384, 16, 8
    torch.manual_seed(0)
    den = build_denoiser(settings, text_dim, n_dom).to(device)
    crop = settings["training"].get("crop_width")
    print(f"config: {'paper' if args.paper else 'embedded default'} {h}x{w}"
          f"{f' (training on {crop}-column windows)' if crop else ''}, "
          f"{count_parameters(den) / 1e6:.2f} M parameters, device {device}, threads {torch.get_num_threads()}")

    tokens = torch.randn(n_dom * 3, n_tok, text_dim)
    mask = torch.ones(n_dom * 3, n_tok, dtype=torch.bool)
    model = make_diffusion_model(den, settings, tokens, mask, seed=0).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    batch = {
        "image": (torch.rand(b_train, 2, h, w) * 2 - 1).to(device),
        "domain": torch.arange(b_train, device=device) % n_dom,
        "prompt": torch.arange(b_train, device=device) % (n_dom * 3),
    }
    times = []
    for i in range(args.train_steps + 1):
        _sync(device)
        t0 = time.perf_counter()
        model.iteration = i
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=args.bf16):
            loss = model(**batch)["loss"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        _sync(device)
        if i:  # the first step warms up allocators and kernels
            times.append(time.perf_counter() - t0)
    step = statistics.median(times)
    where = (f"{'paper' if args.paper else 'embedded default'} {h}x{w}{f', {crop}-column windows' if crop else ''}, "
             f"{device}{', bf16' if args.bf16 else ''}, {torch.get_num_threads()} threads")
    figures[f"{h}x{w}:{crop}"] = {"train_step_s": step, "batch": b_train, "sampling_s_per_scan": {}}
    rows.append({"what": f"generator training step (batch {b_train}; {where})", "median": f"{step:.3g} s"})
    print(f"train step (batch {b_train}): median {step:.3f} s  -> {settings['training']['iterations']} "
          f"iterations ~ {step * settings['training']['iterations'] / 60:.1f} min")
    del opt, model

    den.eval()
    base = first = None
    for spec in args.samplers:
        name, steps = spec.split(":")
        steps = int(steps)
        runs = []
        for r in range(args.repeats):
            _sync(device)
            t0 = time.perf_counter()
            generate(den, 0, tokens[0], mask[0], list(range(r * b_sample, (r + 1) * b_sample)), (h, w),
                     sampler=name, steps=steps, autocast_bf16=args.bf16)
            _sync(device)
            runs.append((time.perf_counter() - t0) / b_sample)
        per_scan = statistics.median(runs)
        base = base or per_scan
        first = first or per_scan
        print(f"sample {name:>8} {steps:4d} steps (batch {b_sample}): median {per_scan:.3f} s/scan  "
              f"ratio {per_scan / base:.2f}")
        figures[f"{h}x{w}:{crop}"]["sampling_s_per_scan"][spec] = per_scan
        rows.append({"what": f"sampling, {name} x {steps} (batch {b_sample}; {where})",
                     "median": f"{per_scan:.3g} s per scan ({per_scan / base:.2f}x the first sampler)"})
    return step, first


def _level_hooks(den, spent: dict) -> None:
    """Add each module's forward time to ``spent[(level, "blocks" | "other")]`` (level None: the stem,
    the middle and the head), through forward hooks."""

    def timed(module: torch.nn.Module, key) -> None:
        module.register_forward_pre_hook(lambda m, a: setattr(m, "_t0", time.perf_counter()))
        module.register_forward_hook(lambda m, a, o: spent.__setitem__(key, spent.get(key, 0.0)
                                                                        + time.perf_counter() - m._t0))

    levels = den.cfg.num_levels
    encoder = [(lv, level, down) for lv, (down, level) in enumerate(zip(den.down, den.enc))]
    decoder = [(levels - 1 - i, level, up) for i, (level, up) in enumerate(zip(den.dec, den.up))]
    for lv, level, resample in encoder + decoder:
        for part in (*level.blocks, level.cross, level.cdfm, level.dafs, resample):
            if part is not None:
                timed(part, (lv, "blocks" if isinstance(part, ResBlock) else "other"))
    for part in (den.stem, den.mid1, den.mid_attn, den.mid_cross, den.mid2, den.head):
        if part is not None:
            timed(part, (None, "other"))


def bench_levels(args) -> tuple[list, dict]:
    """One network evaluation of each --levels residual-block setting, by UNet level, one run."""
    device = torch.device(args.device)
    settings = _settings(args)
    h, w = settings["range_image"]["height"], settings["range_image"]["width"]
    batch = args.batch or settings["sampling"]["batch_size"]
    text_dim, n_tok = 384, 16
    x = torch.randn(batch, 2, h, w, device=device)
    tokens = torch.randn(batch, n_tok, text_dim, device=device)
    mask = torch.ones(batch, n_tok, dtype=torch.bool, device=device)
    rows, figures, first = [], {}, None
    for spec in args.levels:
        blocks = [int(v) for v in spec.split(",")]
        settings["model"]["num_res_blocks"] = blocks[0] if len(blocks) == 1 else blocks
        torch.manual_seed(0)
        den = build_denoiser(settings, text_dim, 8).to(device).eval()
        spent: dict = {}
        _level_hooks(den, spent)
        totals, parts = [], []
        with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16, enabled=args.bf16):
            for r in range(args.repeats + 1):
                spent.clear()
                _sync(device)
                t0 = time.perf_counter()
                den(x, torch.zeros(1, device=device), torch.arange(batch, device=device) % 8, tokens, mask)
                _sync(device)
                if r:  # the first pass warms up allocators and kernels
                    totals.append(time.perf_counter() - t0)
                    parts.append(dict(spent))
        total = statistics.median(totals)
        first = first or total
        split = {key: statistics.median(p.get(key, 0.0) for p in parts) for key in parts[0]}
        print(f"residual blocks {spec} ({count_parameters(den) / 1e6:.2f} M parameters, {h}x{w}, batch {batch}, "
              f"{device}): {total:.3f} s per evaluation, {total / first:.2f}x the first")
        for lv in range(den.cfg.num_levels):
            b, o = split.get((lv, "blocks"), 0.0), split.get((lv, "other"), 0.0)
            print(f"  level {lv} ({h >> lv}x{w >> lv}, {den.cfg.blocks_at(lv)} blocks): residual blocks {b:.3f} s "
                  f"({100 * b / total:.0f} %), the rest {o:.3f} s ({100 * o / total:.0f} %)")
        rest = split.get((None, "other"), 0.0)
        print(f"  stem, middle and head: {rest:.3f} s ({100 * rest / total:.0f} %)")
        rows.append({"what": f"one evaluation, residual blocks {spec} ({h}x{w}, batch {batch}, {device}, "
                             f"{torch.get_num_threads()} threads)",
                     "median": f"{total:.3g} s ({total / first:.2f}x the first setting)"})
        figures[spec] = {"evaluation_s": total, "by_level": {f"{lv}:{kind}": v for (lv, kind), v in split.items()}}
    return rows, figures


def bench_student(args) -> tuple[list, dict]:
    """The student in its DDIM steps against its teacher's solvers, seconds per scan, one run."""
    from omnilidar.generator.checkpoint import load_generator
    from omnilidar.metrics.sampling_timing import TimedSetting, time_settings
    from omnilidar.generator.text import load_prompt_cache

    device = torch.device(args.device)
    student, payload = load_generator(args.student, device=device)
    if not payload.get("student"):
        raise SystemExit(f"{args.student}: not a distilled student")
    teacher, teacher_payload = load_generator(payload["student"]["teacher"], device=device)
    cache = load_prompt_cache(args.prompts)
    print(f"student {args.student} ({payload['student']['steps']} steps of {payload['student']['sampler']}) "
          f"and teacher {payload['student']['teacher']}, device {device}, threads {torch.get_num_threads()}")
    steps, solver = int(payload["student"]["steps"]), payload["student"]["sampler"]
    timed = [TimedSetting(teacher, teacher_payload, spec.split(":")[0], int(spec.split(":")[1])) for spec in args.samplers]
    timed.append(TimedSetting(student, payload, solver, steps))
    domain = "Vehicle" if "Vehicle" in payload["domains"] else payload["domains"][0]
    # The repeats go round the settings in turn: a change of load falls on every setting alike.
    seconds = time_settings(timed, cache, domain, args.batch or payload["config"]["sampling"]["batch_size"],
                            args.repeats, autocast_bf16=args.bf16)
    rows = list(zip([f"teacher {spec}" for spec in args.samplers] + [f"student {solver}:{steps}"], seconds))
    for name, per_scan in rows:
        print(f"{name:>28}: median {per_scan:.3f} s/scan, {rows[0][1] / per_scan:.1f}x faster than {rows[0][0]}")
    return ([{"what": f"{name} ({device}, {torch.get_num_threads()} threads)",
              "median": f"{per_scan:.3g} s per scan ({rows[0][1] / per_scan:.1f}x faster than {rows[0][0]})"}
             for name, per_scan in rows], {name: per_scan for name, per_scan in rows})


if __name__ == "__main__":
    main()
