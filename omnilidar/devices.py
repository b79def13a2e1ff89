"""Which torch device a stage runs on."""

from __future__ import annotations

import torch

from omnilidar.errors import InputError


def resolve_device(name: str, setting: str = "device") -> torch.device:
    """``auto`` (CUDA when available), ``cpu`` or ``cuda[:N]``; a CUDA setting on a machine
    without CUDA is one clear error naming the ``setting``."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise InputError(None, f"{setting} {name}: CUDA is not available on this machine")
    return torch.device(name)


def set_threads(threads: int | None) -> None:
    """CPU threads for torch: a job uses the cores Snakemake gives it (``--threads {threads}``). More
    OpenMP threads than free cores stall at every barrier: on a loaded 2-core machine the samplers
    and the distillation used well under one core with torch's default of two."""
    if threads:
        torch.set_num_threads(int(threads))


def cpu_has_native_bf16() -> bool:
    """Whether this CPU multiplies bf16 natively (AVX512-BF16 or AMX-BF16 in /proc/cpuinfo). There
    bf16 autocast makes the generator's convolutions faster; elsewhere it is emulated and fp32 is kept."""
    try:
        with open("/proc/cpuinfo") as info:
            flags = next((line.split(":", 1)[1].split() for line in info if line.startswith("flags")), [])
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags
