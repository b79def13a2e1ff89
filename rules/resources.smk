# What every job asks the scheduler for, derived from the config in one place:
# gpu (only where the rule's settings run on CUDA and resources.gpus allows it),
# slurm_partition (resources.partitions), runtime (work in the config x a rate in
# resources.rates), mem_mb (host memory: interpreter and data, plus the activations of a
# job that computes on the CPU, from batch x image or points x channels) and cpus_per_task
# (data-loader workers + 1). Every job's request is checked against its partition's limits
# (resources.partition_config, the SLURM executor plugin's own partition file format) when the
# DAG is built, dry runs included. Rules use `resources: **job_resources("name")`.
import functools
import json
import math
import os
import sys
from pathlib import Path

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


class Work:
    """A job's activations in MB when it computes on the CPU (a GPU job holds them on the device);
    a plain number in _RULES is a fixed request instead."""

    def __init__(self, cpu_mb):
        self.cpu_mb = cpu_mb


# Peak resident memory measured on the embedded default (snakemake benchmark files, CPU):
# interpreter, torch and the stage's modules ~450 MB; generator training 1.07 GB at batch 8 of
# 64 x 128 windows x 16 channels (~0.6 kB per pixel-channel of the batch); sampling 0.62 GB at
# batch 8 of 64 x 512 x 16 (~0.05 kB); MinkUNet W16 training 0.68 GB and SPVCNN 1.23 GB at batch
# 2 x 30k points x 16 channels (~0.25 and ~0.8 kB per point-channel); their evaluation ~0.7 GB.
# The constants below round those up; resources.mem_margin covers the rest.
BASE_MB = 1000
WORKER_MB = 1000  # one DataLoader worker process: its own interpreter, torch and prefetched batches
_KB_PER_UNIT = {"generator_train": 0.6, "generator_sample": 0.06, "minkunet": 0.3, "spvcnn": 0.9,
                "inference": 0.1, "detector": 0.5}


def _units_mb(units, kind):
    return units * _KB_PER_UNIT[kind] / 1024


def _channels(width):
    """First-level channels of a segmentor width (W16 -> 16)."""
    return int(width[1:])


def _generator_train_work():
    tr, ri = config["generator"]["training"], config["generator"]["range_image"]
    window = min(tr["crop_width"] or ri["width"], ri["width"])
    units = tr["batch_size"] * ri["height"] * window * config["generator"]["model"]["base_channels"]
    return Work(_units_mb(units, "generator_train"))


def _generator_sample_work(batch):
    ri = config["generator"]["range_image"]
    return Work(_units_mb(batch * ri["height"] * ri["width"] * config["generator"]["model"]["base_channels"],
                          "generator_sample"))


def _segmentor_work(batch, max_points, models, inference=False):
    """The costliest backbone of ``models`` ({name: {width: ...}}) at ``batch`` scans of ``max_points``."""
    points = max_points or 150_000  # no cap: a full 64-beam sweep
    per_backbone = [_units_mb(batch * points * _channels(m["width"]), "inference" if inference else name)
                    for name, m in models.items()]
    return Work(max(per_backbone))


_DOWN = config["downstream"]
_LABELER = _DOWN["labeler"]
_DET = _DOWN["det"]
_GEN_TRAIN = config["generator"]["training"]
_DISTILL = config["generator"]["distillation"]
# A shard's network evaluations: the distilled student's DDIM steps where sampling uses it.
_SAMPLING_STEPS = STUDENT_STEPS if config["generator"]["sampling"]["student"] else config["generator"]["sampling"]["steps"]
_LABELER_MODEL = {_LABELER["backbone"]: _LABELER["model"]}
_LABELER_WORK = _segmentor_work(_LABELER["schedule"]["batch_size"], _LABELER["max_points"], _LABELER_MODEL)
_STUDENT_WORK = _segmentor_work(_DOWN["schedule"]["batch_size"], _DOWN["max_points"], _DOWN["models"])
# A detector's voxels x points per voxel stand in for its points; channels as a W32-sized net.
_DETECTOR_WORK = Work(_units_mb(_DET["schedule"]["batch_size"] * _DET["voxels"]["max_voxels_train"]
                                * _DET["voxels"]["max_points_per_voxel"] * 32, "detector"))
_EVAL = config["evaluation"]
_DOWN_H = RESOURCES["rates"]["downstream_hours"] * 60


@functools.cache
def _split_counts(dataset):
    """{split: scans} of a dataset, counted alike before and after it is indexed (so a training's
    segment chain, which depends on it, stays the same): from its index when that exists for the
    configured root, else from the synthetic world's settings (what it will write) or by listing a
    real root; None for a real root that is missing or unreadable. Read once per planning."""
    root = dataset_root(dataset)
    try:
        with open(f"{DATA}/index/{dataset}.json") as fh:
            index = json.load(fh)
        if index.get("root") == str(root):  # not an index of another root, about to be remade
            return {split: len(entries) for split, entries in index.get("splits", {}).items()}
    except (OSError, ValueError):
        pass
    if is_synthetic(dataset):
        from omnilidar.data.synthetic.shards import planned_split_counts

        return planned_split_counts(dataset, config["synthetic"])
    if not os.path.isdir(root):
        return None
    from omnilidar.data.index import build_index

    try:
        return {split: len(entries) for split, entries in build_index(dataset, root)["splits"].items()}
    except InputError:
        return None


def split_scans(dataset, split):
    """Scans of one split of a dataset (_split_counts), None when they cannot be counted."""
    counts = _split_counts(dataset)
    return None if counts is None else counts.get(split, 0)


def subset_scans(dataset, split, percent):
    """Scans of a label subset (one out of every 100/percent of the split, as make-subset picks them)."""
    from omnilidar.data.subsets import select_every_k

    total = split_scans(dataset, split)
    return None if total is None else len(select_every_k(range(total), float(percent) / 100))


_SCANS_PER_DOMAIN = config["generator"]["sampling"]["scans_per_domain"]


def _study_schedule(w):
    return json.loads(study_settings(w.row))["schedule"]


# What each downstream training trains on, from its wildcards: (schedule, device, rates key, mixing
# or None, a function counting the real scans (None when they cannot be counted; called only for
# an epoch schedule), generated scans).
_TRAININGS = {
    "train_labeler": lambda w: (_LABELER["schedule"], _LABELER["device"], "segmentor", None,
                                lambda: split_scans("semantickitti", "train"), 0),
    "train_supervised": lambda w: (_DOWN["schedule"], _DOWN["device"], "segmentor", None,
                                   lambda: subset_scans(w.dataset, "train", w.pct), 0),
    "train_gda": lambda w: (_DOWN["schedule"], _DOWN["device"], "segmentor", _DOWN["mixing"],
                            lambda: subset_scans(w.dataset, "train", w.pct), len(gda_domains(w)) * _SCANS_PER_DOMAIN),
    "train_gda_curve": lambda w: (_DOWN["schedule"], _DOWN["device"], "segmentor", _DOWN["mixing"],
                                  lambda: subset_scans(w.dataset, "train", w.pct), int(w.scans)),
    "train_curve_pool": lambda w: (_DOWN["schedule"], _DOWN["device"], "segmentor", _DOWN["mixing"],
                                   lambda: subset_scans("semantickitti", "train", w.pct), int(w.scans)),
    "train_study": lambda w: (_study_schedule(w), _DOWN["device"], "segmentor", _DOWN["mixing"],
                              lambda: subset_scans("semantickitti", "train", w.pct), 0 if w.row == "real" else int(w.scans)),
    "train_box_labeler": lambda w: (_DET["labeler"]["schedule"], _DET["device"], "detector", None,
                                    lambda: split_scans("pi3det", f"{w.platform}_train"), 0),
    "train_detector_real": lambda w: (_DET["schedule"], _DET["device"], "detector", None,
                                      lambda: subset_scans("pi3det", f"{w.platform}_train", w.pct), 0),
    "train_detector_gda": lambda w: (_DET["schedule"], _DET["device"], "detector", _DET["mixing"],
                                     lambda: subset_scans("pi3det", f"{w.platform}_train", w.pct), _SCANS_PER_DOMAIN),
}
_TRAININGS |= {f"{rule}_seed": _TRAININGS[rule] for rule in ("train_supervised", "train_gda", "train_gda_curve",
                                                              "train_curve_pool")}


def training_seconds(rule, wildcards):
    """Estimated seconds of one downstream training: steps (schedule.iterations, or epochs over the
    mixed training scans) x batch x seconds per scan and step on the job's device
    (resources.rates.<kind>_scan_step_s on a GPU, <kind>_scan_step_cpu_s on a CPU); None for an
    epoch schedule whose scans cannot be counted."""
    from omnilidar.downstream.schedule import total_iterations

    schedule, device, kind, mixing, count_real, generated = _TRAININGS[rule](wildcards)
    real = 0 if schedule["iterations"] else count_real()  # an iteration schedule needs no count
    if real is None:
        return None
    steps = total_iterations(schedule, real, generated, mixing or {"mode": "concat"})
    on_gpu = cluster_gpus() and uses_cuda(device)
    return steps * schedule["batch_size"] * RESOURCES["rates"][f"{kind}_scan_step_s" if on_gpu else f"{kind}_scan_step_cpu_s"]


def _training_runtime(rule):
    """Minutes each job of a downstream training asks: its share of the estimate where the training
    runs as a chain of segment jobs (training_parts); rates.downstream_hours for an epoch schedule
    whose scans cannot be counted (a real root that is missing)."""
    def runtime(wildcards, input):
        seconds = training_seconds(rule, wildcards)
        return int(_DOWN_H) if seconds is None else _runtime(seconds / training_parts(rule, wildcards))

    return runtime


# rule: (device setting that decides the GPU request: a value, True = always, False = never;
#        mem_mb, runtime in minutes (a number or a function of the wildcards and input), cpus_per_task)
_RULES = {
    "synthesize": (False, 2000, 30, 1),
    "index_dataset": (False, 1000, 10, 1),
    "data_summary": (False, 4000, 30, 1),
    "build_domain": (False, 3000, 60, 1),
    "domains_index": (False, 500, 5, 1),
    "build_heldout_domain": (False, 3000, 60, 1),
    "heldout_domains_index": (False, 500, 5, 1),
    "build_corrupted": (False, 3000, 60, 1),
    "domain_fidelity": (False, 4000, 30, 1),
    "effects_tradeoff": (False, 4000, 60, 1),
    "encode_prompts": (config["generator"]["text"]["device"], Work(1500), 20, 1),
    "train_generator": (_GEN_TRAIN["device"], _generator_train_work(),
                        _runtime(_train_seconds(_GEN_TRAIN["iterations"])), _GEN_TRAIN["num_workers"] + 1),
    "train_single_domain": (_GEN_TRAIN["device"], _generator_train_work(),
                            _runtime(_train_seconds(_baseline_iterations())), _GEN_TRAIN["num_workers"] + 1),
    # A distillation step runs the teacher twice (forward only) beside the student's forward and
    # backward: about 5 forward passes against a training step's 3. The return calibration then
    # samples its scans of every domain with the teacher's and the student's steps. A last round
    # with a critic or distribution matching costs more per step (LAST_ROUND_STEP_COST), and so do
    # the trained generator's substeps (teacher_substep_extra_steps).
    "distill_generator": (_GEN_TRAIN["device"], _generator_train_work(),
                          _runtime(_train_seconds(distillation_iterations(config["generator"])
                                                  + last_round_extra_steps(_DISTILL)
                                                  + teacher_substep_extra_steps(_DISTILL)) * 5 / 3
                                   + sampling_seconds(len(DOMAIN_NAMES) * _DISTILL["return_calibration"],
                                                      sum(n for _, n in calibration_samplers(_DISTILL)) + STUDENT_STEPS)),
                          _GEN_TRAIN["num_workers"] + 1),
    "sample_domain": (config["generator"]["sampling"]["device"],
                      _generator_sample_work(config["generator"]["sampling"]["batch_size"]),
                      _runtime(sampling_seconds(config["generator"]["sampling"]["scans_per_shard"], _SAMPLING_STEPS)), 2),
    "sample_eval": (_EVAL["device"], _generator_sample_work(config["generator"]["sampling"]["batch_size"]),
                    lambda wildcards, input: _runtime(sampling_seconds(
                        config["generator"]["sampling"]["scans_per_shard"], int(wildcards.steps))), 2),
    # Metric extractors self-train where evaluation.extractors.training.device says (CPU by default).
    "train_extractor": (_EVAL["extractors"]["training"]["device"], 8000, 6 * 60, 2),
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
                             + _features_seconds(_EVAL["scans_per_set"] * len(config["generator"]["prompts"]), [1])
                             # every setting timed side by side in the study's job (evaluation.tradeoff.timing)
                             + sampling_seconds(_EVAL["tradeoff"]["timing"]["scans"] * _EVAL["tradeoff"]["timing"]["repeats"],
                                                sum(sum(s) for s in _EVAL["tradeoff"]["samplers"].values())
                                                + (STUDENT_STEPS if _EVAL["tradeoff"]["student"] else 0))), 2),
    # Samples trained and untrained generators itself: evidence.scans per domain, 2 models.
    "generator_evidence": (_EVAL["device"], 16000,
                           _runtime(sampling_seconds(2 * _EVAL["evidence"]["scans"] * len(config["generator"]["prompts"]),
                                                     _EVAL["steps"])), 2),
    "make_subset": (False, 500, 5, 1),
    # The decomposition pool through a domain's scene: a domain build of N scans.
    "simulate_pool": (False, 3000, 60, 1),
    # Importing a user's checkpoint is a small CPU job; training the labeler is the long GPU one.
    "train_labeler": ((False, 4000, 15, 1) if config["downstream"]["labeler"]["checkpoint"] else
                      (_LABELER["device"], _LABELER_WORK, _training_runtime("train_labeler"),
                       _downstream_workers("labeler", "schedule"))),
    "pseudo_label": (_LABELER["device"], _segmentor_work(_LABELER["batch_size"], None, _LABELER_MODEL, True), 60, 2),
    **{rule: (_DOWN["device"], _STUDENT_WORK, _training_runtime(rule), _downstream_workers("schedule"))
       for rule in _TRAININGS if rule.startswith(("train_supervised", "train_gda", "train_curve_pool", "train_study"))},
    "evaluate_segmentor": (_DOWN["device"], _segmentor_work(_DOWN["evaluation"]["batch_size"], None, _DOWN["models"], True),
                           60, 2),
    "gda_result": (False, 1000, 10, 1),
    "gda_curve": (False, 1000, 10, 1),
    # Detection (rules/detection.smk): importing a user's labeler is a small CPU job.
    "train_box_labeler": (_DET["device"], _DETECTOR_WORK, _training_runtime("train_box_labeler"),
                          _downstream_workers("det", "labeler", "schedule")),
    "pseudo_box": (_DET["device"], Work(2000), 60, 2),
    **{rule: (_DET["device"], _DETECTOR_WORK, _training_runtime(rule), _downstream_workers("det", "schedule"))
       for rule in ("train_detector_real", "train_detector_gda")},
    "evaluate_detector": (_DET["device"], Work(2000), 60, 2),
    "pi3det_result": (False, 1000, 10, 1),
}


# Local runs use at most the machine's cores, whatever --cores / -j says (resources.one_job_per_core):
# every job runs torch on one thread, and two per core get no more done in total than one, in twice
# the memory (benchmarks/bench_concurrency.py, docs/benchmarks.md). Lowering
# the provided cores, rather than adding a resource, lets the scheduler sleep while they are
# all busy (with free cores left it re-solves its job selection every second).
MACHINE_CORES = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
if RESOURCES["one_job_per_core"] and workflow.local_exec and (workflow._cores or 0) > MACHINE_CORES:
    workflow.global_resources["_cores"] = MACHINE_CORES


def _partition_limits():
    """{partition: PartitionLimits} from resources.partition_config, a partition file in the SLURM
    executor plugin's format read by the plugin's own reader; None without a file, or without the
    plugin (then nothing is submitted to SLURM either)."""
    source = RESOURCES["partition_config"]
    if source is None:
        return None
    try:
        from snakemake_executor_plugin_slurm.partitions import read_partition_file
    except ImportError:
        return None
    path = Path(source) if os.path.isabs(source) else Path(workflow.basedir) / source
    if not path.is_file():
        sys.exit(f"Invalid configuration: resources.partition_config {source}: no such file")
    # The plugin reads the same file when no --slurm-partition-config is given.
    os.environ.setdefault("SNAKEMAKE_SLURM_PARTITIONS", str(path))
    return {p.name: p.limits for p in read_partition_file(path)}


PARTITION_LIMITS = _partition_limits()

# The SLURM profile's account until the user sets one (workflow/profiles/slurm/config.yaml), and
# sbatch's own variable that sets it instead. Optional, so not an `envvars:` entry (that would
# require it on every machine); only the submitting Snakemake reads it.
ACCOUNT_PLACEHOLDER = "CHANGE_ME"
ACCOUNT_VARIABLE = "SBATCH_ACCOUNT"


def cluster_has_accounting():
    """False when the running cluster keeps no accounting (AccountingStorageType none), so any
    account is accepted; True when it does or when no cluster answers."""
    import subprocess

    try:
        out = subprocess.run(["scontrol", "show", "config"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return True
    return "accounting_storage/none" not in out


def _check_account():
    defaults = workflow.resource_settings.default_resources
    account = defaults.get("slurm_account") if defaults is not None else None
    if (account is not None and str(account.raw).strip("'\"") == ACCOUNT_PLACEHOLDER
            and not os.environ.get(ACCOUNT_VARIABLE) and cluster_has_accounting()):
        sys.exit(f"The SLURM account is the profile's placeholder {ACCOUNT_PLACEHOLDER}: export SBATCH_ACCOUNT=<account>, "
                 "pass --default-resources slurm_account=<account>, or set it in workflow/profiles/slurm/config.yaml")


_check_account()


def cluster_gpus():
    """Whether jobs may ask for GPUs: resources.gpus true / false, or auto = where the GPU
    partition's limits allow any (no partition limits known: wherever the stage runs on CUDA)."""
    setting = RESOURCES["gpus"]
    if setting != "auto":
        return bool(setting)
    if PARTITION_LIMITS is None:
        return True
    gpu = PARTITION_LIMITS.get(RESOURCES["partitions"]["gpu"])
    return gpu is not None and gpu.max_gpu > 0


_REMEDY = {"mem_mb": "resources.mem_mb: {{{rule}: MB}}", "runtime": "resources.runtime: {{{rule}: minutes}}",
           "gpu": "resources.gpus: false (no GPU anywhere)", "cpus_per_task": "fewer num_workers"}


class PartitionLimitExceeded(Exception):
    """A job asks more than its partition allows."""


def check_partition_fit(rule, partition, mem_mb, cpus, gpus, minutes):
    """One clear error naming the rule, the request and the limit it exceeds."""
    if PARTITION_LIMITS is None:
        return
    where = f"resources.partition_config {RESOURCES['partition_config']}"
    limits = PARTITION_LIMITS.get(partition)
    if limits is None:
        raise PartitionLimitExceeded(f"Rule {rule} asks for partition {partition}, which is not in {where}")
    asks = [("mem_mb", mem_mb, limits.max_mem_mb, "MB of memory"), ("cpus_per_task", cpus, limits.max_cpus_per_task, "CPUs"),
            ("gpu", gpus, limits.max_gpu, "GPUs"), ("runtime", minutes, limits.max_runtime, "minutes")]
    for key, asked, limit, unit in asks:
        if asked > limit:
            raise PartitionLimitExceeded(
                f"Rule {rule} asks {asked} {unit} ({key}) but partition {partition} allows {limit:g} ({where}); "
                f"lower the work in the config, raise the limit there, or set {_REMEDY[key].format(rule=rule)}")


def _mem_mb(work, gpus, cpus):
    """Host memory (MB) of a job: fixed for a plain number, else derived from its Work."""
    if not isinstance(work, Work):
        return work
    workers = max(0, cpus - 1)
    mb = BASE_MB + workers * WORKER_MB + (0 if gpus else work.cpu_mb)
    return int(math.ceil(RESOURCES["mem_margin"] * mb))


def _job_gpus(rule):
    device = _RULES[rule][0]
    if cluster_gpus() and (device is True or (device is not False and uses_cuda(device))):
        return RESOURCES["generator_gpus"] if rule.startswith(("train_generator", "train_single_domain")) else 1
    return 0


def _segment_ends(rule, iterations, seconds_per_iteration):
    """Where a training too long for its partition's time limit is cut into a chain of jobs that each
    fit (the iterations each segment ends at, the last job going on to ``iterations``); [] when
    the whole training fits, or no limit is known."""
    limits = PARTITION_LIMITS and PARTITION_LIMITS.get(RESOURCES["partitions"]["gpu" if _job_gpus(rule) else "cpu"])
    if not limits or _runtime(iterations * seconds_per_iteration) <= limits.max_runtime:
        return []
    per_job = int((limits.max_runtime - RESOURCES["setup_min"]) * 60 / (RESOURCES["margin"] * seconds_per_iteration))
    if per_job < 1:
        sys.exit(f"Invalid configuration: one iteration of {rule} does not fit the partition's time limit "
                 f"({limits.max_runtime:g} minutes, resources.partition_config); raise it or lower the work")
    return list(range(per_job, iterations, per_job))


# The generator's training as a chain of segment jobs where it outlasts its partition's time limit
# (rules/generator.smk): each segment asks for its own share of the time.
GENERATOR_SEGMENT_ENDS = _segment_ends("train_generator", _GEN_TRAIN["iterations"], _train_seconds(1))
_RULES["train_generator_segment"] = _RULES["train_generator"]
if GENERATOR_SEGMENT_ENDS:
    _device, _work, _, _cpus = _RULES["train_generator"]
    _RULES["train_generator_segment"] = (_device, _work, _runtime(GENERATOR_SEGMENT_ENDS[0] * _train_seconds(1)), _cpus)
    _RULES["train_generator"] = (_device, _work, _runtime(
        (_GEN_TRAIN["iterations"] - GENERATOR_SEGMENT_ENDS[-1]) * _train_seconds(1)), _cpus)


def generator_segment(preset, until):
    """The record of the segment ending at ``until`` (rule train_generator_segment)."""
    return f"{GENERATOR}/{preset}/segments/until_{until}.json"


def previous_generator_segment(w):
    """A segment's (or the final job's) predecessor in the chain: [] for the first."""
    until = int(w.until) if hasattr(w, "until") else float("inf")
    ends = [e for e in GENERATOR_SEGMENT_ENDS if e < until]
    return [generator_segment(w.preset, ends[-1])] if ends else []


# Downstream trainings (labelers, students, detectors) longer than their partition allows run as a
# chain of segment jobs too: job k of n trains the k-th n-th of the run's own iteration count
# (`--segment k/n`, which the trainer resolves once it has counted its scans) and leaves its state in
# the training's work folder; the training's own job resumes the last part and writes the weights.
# n comes from training_seconds, which counts scans alike before and after indexing (split_scans).
_IMPORTED = {
    "train_labeler": lambda w: bool(config["downstream"]["labeler"]["checkpoint"]),
    "train_box_labeler": lambda w: bool(labeler_checkpoint(w.platform)),
}


def training_parts(rule, wildcards):
    """How many jobs a downstream training runs as: 1, or a chain each within its partition's limit."""
    if _IMPORTED.get(rule, lambda w: False)(wildcards):
        return 1
    limits = PARTITION_LIMITS and PARTITION_LIMITS.get(RESOURCES["partitions"]["gpu" if _job_gpus(rule) else "cpu"])
    if not limits:  # a local run: no limit to fit
        return 1
    seconds = training_seconds(rule, wildcards)
    if seconds is None or _runtime(seconds) <= limits.max_runtime:
        return 1
    per_job = (limits.max_runtime - RESOURCES["setup_min"]) * 60 / RESOURCES["margin"]
    if per_job <= 0:
        sys.exit(f"Invalid configuration: resources.setup_min leaves {rule} no time within the partition's limit "
                 f"({limits.max_runtime:g} minutes, resources.partition_config)")
    return math.ceil(seconds / per_job)


def segment_record(final, part, parts):
    """The record segment job ``part`` of ``parts`` of the training writing ``final`` leaves
    (<folder>/segments/<name>.<part>of<parts>.json); with pattern strings, the segment rule's output."""
    folder, name = os.path.split(os.path.splitext(final)[0])
    return f"{folder}/segments/{name}.{part}of{parts}.json"


def segment_output(final):
    """Output pattern of a training rule's segment jobs."""
    return segment_record(final, "{part,[0-9]+}", "{parts,[0-9]+}")


def previous_segment(rule, final):
    """Input function of a training and its segments: the segment job before this one in
    the chain ([] for the first, and for a training that runs as one job). Seed variants name their
    output <run>_seed<seed>.pt after ``final``'s <run>.pt."""
    def previous(w):
        parts = int(w.parts) if hasattr(w, "parts") else training_parts(rule, w)
        part = int(w.part) if hasattr(w, "part") else parts
        if part <= 1:
            return []
        path = final
        if hasattr(w, "seed") and "{seed}" not in final:
            path = path.replace(".pt", "_seed{seed}.pt")
        return [segment_record(path.format(**{k: getattr(w, k) for k in w.keys()}), part - 1, parts)]

    return previous


def segment_flag(wildcards):
    """The trainer's --segment argument in a segment job ('' in the training's own job)."""
    if not hasattr(wildcards, "part"):
        return ""
    if not 1 <= int(wildcards.part) < int(wildcards.parts):
        raise ValueError(f"segment {wildcards.part} of {wildcards.parts}: segment jobs are 1..{int(wildcards.parts) - 1}")
    return f"--segment {wildcards.part}/{wildcards.parts}"


def job_resources(rule):
    """Resources of one rule (see _RULES); config resources.mem_mb / resources.runtime replace them
    per rule. The request is checked against its partition when the job is created (dry runs too)."""
    device, work, runtime, cpus = _RULES[rule]
    gpus = _job_gpus(rule)
    cpus = cpus * max(1, gpus)
    mem_mb = RESOURCES["mem_mb"].get(rule, _mem_mb(work, gpus, cpus))
    runtime = RESOURCES["runtime"].get(rule, runtime)
    partition = RESOURCES["partitions"]["gpu" if gpus else "cpu"]

    def checked_mem_mb(wildcards, input):
        check_partition_fit(rule, partition, mem_mb, cpus, gpus, runtime(wildcards, input) if callable(runtime) else runtime)
        return mem_mb

    out = {"mem_mb": checked_mem_mb, "runtime": runtime, "cpus_per_task": cpus, "slurm_partition": partition}
    if os.environ.get(ACCOUNT_VARIABLE):  # the plugin would pass the profile's -A over sbatch's variable
        out["slurm_account"] = os.environ[ACCOUNT_VARIABLE]
    if gpus:
        out["gpu"] = gpus
    return out


def generator_launcher():
    """`omnilidar` for one GPU, torchrun with one process per GPU for more (DDP inside one job)."""
    n = RESOURCES["generator_gpus"]
    return "omnilidar" if n == 1 else f"torchrun --standalone --nproc_per_node {n} $(which omnilidar)"
