# What every job asks the scheduler for, derived from the config in one place:
# gpu (only where the rule's settings run on CUDA), slurm_partition (config
# resources.partitions), runtime (work in the config x a rate in resources.rates),
# mem_mb and cpus_per_task (data-loader workers + 1). Rules use `resources: **job_resources("name")`.
import math
import os
import sys

RESOURCES = config["resources"]
# Rates are for 64x1024 images; smaller images scale them down.
_PIXELS = config["generator"]["range_image"]["height"] * config["generator"]["range_image"]["width"] / (64 * 1024)


if config["generator"]["training"]["batch_size"] % RESOURCES["generator_gpus"]:
    sys.exit(f"Invalid configuration: generator.training.batch_size {config['generator']['training']['batch_size']} "
             f"does not split over resources.generator_gpus {RESOURCES['generator_gpus']} processes.")


def _runtime(seconds):
    """Minutes asked for ``seconds`` of estimated work (with margin and set-up time)."""
    return int(math.ceil(RESOURCES["setup_min"] + RESOURCES["margin"] * seconds / 60))


def uses_cuda(device):
    """Whether a device setting runs on CUDA where it is available (auto, cuda, cuda:N)."""
    return not str(device).startswith("cpu")


def _train_seconds(iterations):
    tr = config["generator"]["training"]
    width = config["generator"]["range_image"]["width"]
    windows = min(tr["crop_width"] or width, width) / width  # azimuth-window training costs its window
    per_step = RESOURCES["rates"]["train_step_s"] * tr["batch_size"] / 16 * _PIXELS * windows
    return iterations * per_step / (RESOURCES["generator_gpus"] ** 0.9)  # ~90 % DDP scaling


def sampling_seconds(scans, steps):
    return scans * steps * RESOURCES["rates"]["sample_step_s"] * _PIXELS


def _features_seconds(scans, metrics):
    return scans * max(1, len(metrics)) * RESOURCES["rates"]["feature_scan_s"] * _PIXELS


def _baseline_iterations():
    return config["evaluation"]["generation_quality"]["baseline_iterations"] or config["generator"]["training"]["iterations"]


def _evaluation_runtime(sets, metrics):
    """Scoring ``sets`` scan sets (real and generated) of scans_per_set scans; samples come from shard jobs."""
    return _runtime(_features_seconds(sets * config["evaluation"]["scans_per_set"], metrics))


def _downstream_workers(*keys):
    node = config["downstream"]
    for key in keys:
        node = node[key]
    return node["num_workers"] + 1


_EVAL = config["evaluation"]
_DOWN_H = RESOURCES["rates"]["downstream_hours"] * 60
# rule: (device setting that decides the GPU request: a value, True = always, False = never;
#        mem_mb, runtime in minutes (a number or a function of the wildcards), cpus_per_task)
_RULES = {
    "synthesize": (False, 2000, 30, 1),
    "index_dataset": (False, 1000, 10, 1),
    "data_summary": (False, 4000, 30, 1),
    "build_domain": (False, 3000, 60, 1),
    "domains_index": (False, 500, 5, 1),
    "build_corrupted": (False, 3000, 60, 1),
    "domain_fidelity": (False, 4000, 30, 1),
    "effects_tradeoff": (False, 4000, 60, 1),
    "encode_prompts": (config["generator"]["text"]["device"], 8000, 20, 1),
    "train_generator": (True, 32000, _runtime(_train_seconds(config["generator"]["training"]["iterations"])),
                        config["generator"]["training"]["num_workers"] + 1),
    "train_single_domain": (True, 32000, _runtime(_train_seconds(_baseline_iterations())),
                            config["generator"]["training"]["num_workers"] + 1),
    "sample_domain": (config["generator"]["sampling"]["device"], 16000,
                      _runtime(sampling_seconds(config["generator"]["sampling"]["scans_per_shard"],
                                                config["generator"]["sampling"]["steps"])), 2),
    "sample_eval": (_EVAL["device"], 16000,
                    lambda w: _runtime(sampling_seconds(config["generator"]["sampling"]["scans_per_shard"], int(w.steps))), 2),
    # Metric extractors train on the CPU (omnilidar.metrics.extractors.training).
    "train_extractor": (False, 8000, 6 * 60, 2),
    # Real and generated sets: 8 domains x (full + baseline + real).
    "generation_quality": (_EVAL["device"], 32000,
                           _evaluation_runtime(3 * len(config["generator"]["prompts"]), _EVAL["generation_quality"]["metrics"]), 2),
    "ablation_table": (_EVAL["device"], 32000,
                       _evaluation_runtime((1 + len(_EVAL["ablation"]["presets"])) * len(config["generator"]["prompts"]),
                                           _EVAL["ablation"]["metrics"]), 2),
    "kitti360_generation": (_EVAL["device"], 16000, _evaluation_runtime(3, _EVAL["kitti360"]["metrics"]), 2),
    "sampler_tradeoff": (_EVAL["device"], 16000,
                         _runtime(_features_seconds(
                             sum(len(s) for s in _EVAL["tradeoff"]["samplers"].values()) * _EVAL["tradeoff"]["scans"]
                             * len(_EVAL["tradeoff"]["domains"] or config["generator"]["prompts"]), [1])
                             + _features_seconds(_EVAL["scans_per_set"] * len(config["generator"]["prompts"]), [1])), 2),
    # Samples trained and untrained generators itself: evidence.scans per domain, 2 models.
    "generator_evidence": (_EVAL["device"], 16000,
                           _runtime(sampling_seconds(2 * _EVAL["evidence"]["scans"] * len(config["generator"]["prompts"]),
                                                     _EVAL["steps"])), 2),
    "make_subset": (False, 500, 5, 1),
    # The decomposition pool through a domain's scene: a domain build of N scans.
    "simulate_pool": (False, 3000, 60, 1),
    # Importing a user's checkpoint is a small CPU job; training the labeler is the long GPU one.
    "train_labeler": ((False, 4000, 15, 1) if config["downstream"]["labeler"]["checkpoint"] else
                      (config["downstream"]["labeler"]["device"], 16000, _DOWN_H, _downstream_workers("labeler", "schedule"))),
    "pseudo_label": (config["downstream"]["labeler"]["device"], 8000, 60, 2),
    "train_supervised": (config["downstream"]["device"], 16000, _DOWN_H, _downstream_workers("schedule")),
    "train_gda": (config["downstream"]["device"], 16000, _DOWN_H, _downstream_workers("schedule")),
    "train_gda_curve": (config["downstream"]["device"], 16000, _DOWN_H, _downstream_workers("schedule")),
    "evaluate_segmentor": (config["downstream"]["device"], 8000, 60, 2),
    "gda_result": (False, 1000, 10, 1),
    "gda_curve": (False, 1000, 10, 1),
    # Detection (rules/detection.smk): importing a user's labeler is a small CPU job.
    "train_box_labeler": (config["downstream"]["det"]["device"], 16000, _DOWN_H, _downstream_workers("det", "labeler", "schedule")),
    "pseudo_box": (config["downstream"]["det"]["device"], 8000, 60, 2),
    "train_detector": (config["downstream"]["det"]["device"], 16000, _DOWN_H, _downstream_workers("det", "schedule")),
    "evaluate_detector": (config["downstream"]["det"]["device"], 8000, 60, 2),
    "pi3det_result": (False, 1000, 10, 1),
}


# Local runs use at most the machine's cores, whatever --cores / -j says (resources.one_job_per_core):
# every job runs torch on one thread, and two per core get less done in total than one (cache
# and context-switch contention; benchmarks/bench_concurrency.py, README "Benchmarks"). Lowering
# the provided cores, rather than adding a resource, lets the scheduler sleep while they are
# all busy (with free cores left it re-solves its job selection every second).
MACHINE_CORES = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
if RESOURCES["one_job_per_core"] and workflow.local_exec and (workflow._cores or 0) > MACHINE_CORES:
    workflow.global_resources["_cores"] = MACHINE_CORES


def job_resources(rule):
    """Resources of one rule (see _RULES); config resources.mem_mb / resources.runtime replace them per rule."""
    device, mem_mb, runtime, cpus = _RULES[rule]
    gpus = 0
    if device is True or (device is not False and uses_cuda(device)):
        gpus = RESOURCES["generator_gpus"] if rule in ("train_generator", "train_single_domain") else 1
    out = {
        "mem_mb": RESOURCES["mem_mb"].get(rule, mem_mb),
        "runtime": RESOURCES["runtime"].get(rule, runtime),
        "cpus_per_task": cpus * max(1, gpus),
        "slurm_partition": RESOURCES["partitions"]["gpu" if gpus else "cpu"],
    }
    if gpus:
        out["gpu"] = gpus
    return out


def generator_launcher():
    """`omnilidar` for one GPU, torchrun with one process per GPU for more (DDP inside one job)."""
    n = RESOURCES["generator_gpus"]
    return "omnilidar" if n == 1 else f"torchrun --standalone --nproc_per_node {n} $(which omnilidar)"
