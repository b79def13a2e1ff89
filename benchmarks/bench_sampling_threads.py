"""Sampling with torch's default threads against one thread, alone and beside another busy job.

    python benchmarks/bench_sampling_threads.py [--scans 8] [--steps 10]

The workflow runs each job on the cores Snakemake gives it (one on a local CPU run: `--threads
{threads}`). This measures why for the generator's sampler: the embedded default's network (random
weights, the Vehicle prompt's shape) samples --scans scans with UniPC in its own process, with
torch's default thread count (every core) and with one thread, first alone and then while a
neighbour process keeps one core busy with single-threaded matrix products (another job). Prints
seconds per scan, the sampler's CPU use (CPU seconds over wall seconds) and the ratios.
"""

from __future__ import annotations

import argparse
import copy
import multiprocessing as mp
import os
import time

import torch

import bench_record


def busy(stop) -> None:
    """Another job: single-threaded matrix products until told to stop."""
    torch.set_num_threads(1)
    a = torch.randn(512, 512)
    while not stop.is_set():
        a = torch.tanh(a @ a)


def sample(threads: int | None, scans: int, steps: int, results) -> None:
    from omnilidar.config import section_defaults
    from omnilidar.generator.diffusion import generate
    from omnilidar.generator.unet import build_denoiser

    if threads:
        torch.set_num_threads(threads)
    settings = copy.deepcopy(section_defaults("generator"))
    h, w = settings["range_image"]["height"], settings["range_image"]["width"]
    torch.manual_seed(0)
    den = build_denoiser(settings, 384, 8).eval()
    tokens, mask = torch.randn(16, 384), torch.ones(16, dtype=torch.bool)
    generate(den, 0, tokens, mask, [0], (h, w), sampler="unipc", steps=2)  # warm-up
    wall, cpu = time.perf_counter(), time.process_time()
    generate(den, 0, tokens, mask, list(range(scans)), (h, w), sampler="unipc", steps=steps)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    results.put({"threads": torch.get_num_threads(), "s_per_scan": wall / scans, "cpu_use": cpu / wall})


def run(threads: int | None, neighbour: bool, args) -> dict:
    ctx = mp.get_context("spawn")
    stop, results = ctx.Event(), ctx.Queue()
    other = ctx.Process(target=busy, args=(stop,)) if neighbour else None
    if other:
        other.start()
        time.sleep(1.0)
    proc = ctx.Process(target=sample, args=(threads, args.scans, args.steps, results))
    proc.start()
    row = results.get()
    proc.join()
    if other:
        stop.set()
        other.join()
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=8)
    ap.add_argument("--steps", type=int, default=10)
    bench_record.out_arg(ap)
    args = ap.parse_args()
    cores = len(os.sched_getaffinity(0))
    rows, figures = [], {}
    for neighbour in (False, True):
        where = "beside a busy single-threaded job" if neighbour else "alone"
        measured = {}
        for threads in (None, 1):
            r = run(threads, neighbour, args)
            measured[threads] = r
            print(f"{where}, {r['threads']} thread(s): {r['s_per_scan']:.3f} s per scan, CPU use {r['cpu_use']:.2f}",
                  flush=True)
            rows.append({"what": f"sampling, unipc x {args.steps}, {where}, {r['threads']} thread(s) "
                                 f"({cores} cores)",
                         "median": f"{r['s_per_scan']:.3g} s per scan, CPU use {r['cpu_use']:.2f}"})
        ratio = measured[None]["s_per_scan"] / measured[1]["s_per_scan"]
        print(f"{where}: default threads / one thread, seconds per scan: {ratio:.2f}")
        rows.append({"what": f"ratio, {where}: torch's default threads / one thread", "median": f"{ratio:.2f}"})
        figures["beside" if neighbour else "alone"] = {"default": measured[None], "one": measured[1], "ratio": ratio}
    bench_record.write(args.out, rows, figures)


if __name__ == "__main__":
    main()
