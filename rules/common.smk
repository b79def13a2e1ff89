# Helpers shared by the workflow: validated config, per-stage settings, code hashes, shards.
import json
import os
import re
import sys

from omnilidar.config import validate, workflow_file
from omnilidar.data_source import describe as describe_sources, mixed as sources_mixed, record as data_source_record
from omnilidar.errors import InputError
from omnilidar.generator.distill_steps import (calibration_samplers, distillation_iterations, last_round_extra_steps,
                                               student_steps, teacher_substep_extra_steps)
from omnilidar.manifest import listing_digest
from omnilidar.provenance import code_manifest, command_code_hash, command_modules, package_versions
from omnilidar.rerun_reasons import record_code_manifest

try:
    # Fills every default from workflow/schemas/ and rejects unknown keys.
    validate(config, source="config (config/config.yaml and --config/--configfile overrides)")
except InputError as err:
    sys.exit(f"Invalid configuration: {err}")

DATA = config["data_dir"]
# One software environment for every rule: the omnilidar package and its dependencies.
ENV = "../workflow/envs/omnilidar.yaml"
# Scheduling: the chain that ends in generated, pseudo-labelled scans (domains -> generator ->
# samples, the labelers, their labels) gates every GDA run, so when several jobs are ready its
# jobs start first and runs that need only real data fill the other slots.
GDA_CHAIN_PRIORITY = 10


def training_priority(wildcards):
    """Segmentation trainings longest first when several are ready: SPVCNN's (about 1.3x a
    MinkUNet step) before MinkUNet's, and every training before the evaluations, so that the
    cores finish on short jobs together instead of one core waiting on a long one."""
    return 2 if wildcards.backbone == "spvcnn" else 1


def settings(*keys, drop=()):
    """A config section as one JSON string: Snakemake compares params by value
    repr, so the whole section travels as one value and any change reruns.
    ``drop`` leaves out subsections the stage never reads (e.g. sampling
    settings for training), so changing them does not rerun it."""
    node = config
    for key in keys:
        node = node[key]
    if drop:
        node = {k: v for k, v in node.items() if k not in drop}
    return json.dumps(node, sort_keys=True)


def job_work_dir(output):
    """A job's own folder for resumable state, named after its output (work/<output without suffix>);
    a segment job's (<folder>/segments/<name>.<k>of<n>.json) is its training's, work/<folder>/<name>.
    What is in it is resumed only when its recorded provenance matches the job (see README)."""
    segment = re.fullmatch(r"(.+)/segments/(.+)\.[0-9]+of[0-9]+\.json", output)
    return f"work/{segment[1]}/{segment[2]}" if segment else f"work/{os.path.splitext(output)[0]}"


# Package versions (torch, numpy, spconv, mamba, text encoder, ...): recorded in every result
# and checkpoint; they rerun stages only where rerun_on_version_change asks for it.
VERSIONS = package_versions()
VERSIONS_RECORD = ".snakemake/omnilidar_versions.json"


def _versions_rerun(command):
    wanted = config["rerun_on_version_change"]
    return wanted is True or (isinstance(wanted, list) and command in wanted)


def code(command, exclude=()):
    """Content hash of the package code an ``omnilidar <command>`` runs (with the package
    versions appended where rerun_on_version_change asks for them)."""
    digest = command_code_hash(command, exclude=exclude)
    # The files behind the hash, so `omnilidar why` can name the ones that changed.
    record_code_manifest(digest, code_manifest(*command_modules(command), exclude=exclude))
    if _versions_rerun(command):
        digest = f"{digest} {json.dumps(VERSIONS, sort_keys=True)}"
    return digest


def result_code(command):
    """Code hash of a result rule: its command and the HTML table written after it."""
    return f"{code(command)} {code('result-table')}"


def with_table(command):
    """A result rule's command, then its result as an HTML table (for the report)."""
    return f"{command} && omnilidar result-table {{output.json}} --out {{output.table}} >> {{log}} 2>&1"


def _report_version_changes():
    """Say which package versions differ from the last successful run of this workflow."""
    try:
        with open(VERSIONS_RECORD) as fh:
            before = json.load(fh)
    except (OSError, ValueError):
        return
    changed = {k: (before.get(k), v) for k, v in VERSIONS.items() if before.get(k) != v}
    if changed:
        what = ", ".join(f"{k} {a} -> {b}" for k, (a, b) in sorted(changed.items()))
        wanted = config["rerun_on_version_change"]
        effect = ("every stage reruns" if wanted is True else
                  f"stages {', '.join(wanted)} rerun" if wanted else
                  "outputs are kept (rerun_on_version_change: true, or a list of stages, reruns them)")
        print(f"Package versions changed since the last run: {what}; {effect}.", file=sys.stderr)


_report_version_changes()


def report_failed_jobs(snakemake_logs):
    """Print each failed job's error line(s), read from its own log, on the terminal
    (Snakemake itself only names the log). Used by the Snakefile's onerror handler,
    which gets the run's log file(s)."""
    text = ""
    for name in [snakemake_logs] if isinstance(snakemake_logs, str) else list(snakemake_logs or []):
        try:
            with open(name) as fh:
                text += fh.read()
        except OSError:
            continue
    for path in dict.fromkeys(re.findall(r"log: (\S+) \(check log file", text)):
        try:
            with open(path) as fh:
                lines = [line.rstrip() for line in fh if line.strip()]
        except OSError:
            continue
        errors = [line for line in lines if ": error: " in line] or lines[-1:]
        for line in errors[-3:]:
            print(f"{path}: {line}", file=sys.stderr)


def record_versions():
    """Called on success: the versions the outputs now on disk were made with."""
    os.makedirs(os.path.dirname(VERSIONS_RECORD), exist_ok=True)
    with open(VERSIONS_RECORD, "w") as fh:
        json.dump(VERSIONS, fh, indent=1, sort_keys=True)


def dataset_root(name):
    """The dataset's root: the configured real root, or where the synthetic world writes it."""
    root = config["datasets"][name]["root"]
    return root if root is not None else f"{DATA}/synthetic/{name}"


def root_listing(root):
    """Listing digest of a real dataset root (omnilidar.manifest.listing_digest), "missing" when absent."""
    return listing_digest(root)["digest"] if os.path.isdir(root) else "missing"


def is_synthetic(name):
    return config["datasets"][name]["root"] is None


def synthetic_shards(name):
    """Shard names (sequences, platforms or splits) the synthetic world writes for one dataset."""
    from omnilidar.data.synthetic.shards import shard_names

    return shard_names(name, config["synthetic"])


# Where each dataset's shard lies below its synthetic root (the dataset's own layout), and
# the shard names the workflow accepts.
SYNTHETIC_SHARD_LAYOUT = {
    "semantickitti": ("sequences/{shard}", r"\d\d"),
    "kitti360": ("data_3d_raw/2013_05_28_drive_{shard}_sync", r"\d{4}"),
    "pi3det": ("{shard}", r"vehicle|drone|quadruped"),
    "nuscenes": ("{shard}", r"train|val"),
}


def synthetic_shard_settings(name, shard_dir):
    """The synthetic settings one shard is made from (the shared keys and its own dataset entry),
    as one JSON string: a change to another dataset, platform or sequence leaves it as it is."""
    from omnilidar.data.synthetic.shards import shard_settings

    return json.dumps(shard_settings(config["synthetic"], name, synthetic_shard(name, shard_dir)), sort_keys=True)


def synthetic_shard_dirs(name):
    layout, _ = SYNTHETIC_SHARD_LAYOUT[name]
    return [f"{DATA}/synthetic/{name}/{layout.format(shard=s)}" for s in synthetic_shards(name)]


def synthetic_shard_dir_regex():
    """Wildcard constraint of a shard folder below its dataset's synthetic root, tied to the
    dataset in the path before it (so that pi3det/train or nuscenes/sequences/08 match nothing)."""
    alternatives = []
    for name, (layout, shard) in SYNTHETIC_SHARD_LAYOUT.items():
        before, after = layout.split("{shard}")
        alternatives.append(f"(?<=/{name}/){re.escape(before)}(?:{shard}){re.escape(after)}")
    return "|".join(alternatives)


def synthetic_shard(name, shard_dir):
    """The shard name in a shard folder of one dataset (sequences/08 -> 08)."""
    before, after = SYNTHETIC_SHARD_LAYOUT[name][0].split("{shard}")
    return shard_dir[len(before) : len(shard_dir) - len(after)]


def sample_shards(domain, scans=None):
    """Sample shard directories holding a domain's first ``scans`` scans (default scans_per_domain;
    a larger count names the shards past it, which the sample rule makes alike)."""
    sampling = config["generator"]["sampling"]
    scans = sampling["scans_per_domain"] if scans is None else int(scans)
    return [f"{DATA}/samples/{domain}/shard_{k}" for k in range(-(-scans // sampling["scans_per_shard"]))]


# Keys of the domains section that are settings, not domains (omnilidar.domains.spec).
DOMAIN_SECTION_KEYS = ("range_image", "corrupted", "fidelity", "tradeoff")
DOMAIN_NAMES = [k for k in config["domains"] if k not in DOMAIN_SECTION_KEYS]
EFFECT_MODULES = ("beam_missing", "beam_reduction", "fog", "rain", "snow", "wet_ground")
# The corrupted val sets (rules/domains.smk builds them; the downstream helpers below name them).
CORRUPTED = f"{DATA}/semantickitti_c"


def domain_label(name):
    """The domain's label (its name in the domains index and the prompt pools)."""
    return config["domains"][name]["label"]


def domains_settings():
    """The domains section as the domain stage's jobs read it: without each domain's
    heldout_split, which only its held-out set reads (naming one rebuilds nothing else)."""
    return json.dumps({k: _without_heldout(v) for k, v in config["domains"].items()}, sort_keys=True)


def _without_heldout(entry):
    return {k: v for k, v in entry.items() if k != "heldout_split"} if isinstance(entry, dict) else entry


def domain_settings(name):
    """What one domain's build reads: its own entry and the image geometry, so that
    editing another domain's effects does not rebuild this one."""
    section = config["domains"]
    return json.dumps({"range_image": section["range_image"], name: _without_heldout(section[name])}, sort_keys=True)


def _heldout_entry(name):
    """One domain's held-out reference set: its entry on its heldout_split, in one shard."""
    return _without_heldout(config["domains"][name]) | {"split": heldout_split(name), "num_shards": 1}


def heldout_domain_settings(name):
    """What one domain's held-out build reads (as domain_settings)."""
    return json.dumps({"range_image": config["domains"]["range_image"], name: _heldout_entry(name)}, sort_keys=True)


def heldout_domains_settings():
    """The domains section as the held-out sets' index reads it."""
    return json.dumps({k: _heldout_entry(k) if k in DOMAIN_NAMES else _without_heldout(v)
                       for k, v in config["domains"].items()}, sort_keys=True)


def heldout_split(name):
    """The split a domain's held-out set comes from; a config error if it has none or its training split."""
    entry = config["domains"][name]
    split = entry.get("heldout_split")
    if not split or split == entry["split"]:
        sys.exit(f"Invalid configuration: domains.{name}.heldout_split is {split!r} (training split {entry['split']!r}); "
                 "evaluation.tradeoff.reference: heldout needs a held-out split of the domain's source for every domain")
    return split


def domain_code(name):
    """Code hash of build-domain without the effect modules this domain does not use."""
    used = {effect["name"] for effect in config["domains"][name]["effects"]}
    unused = tuple(f"omnilidar.domains.effects.{m}" for m in EFFECT_MODULES if m not in used)
    return code("build-domain", exclude=unused)


def _check_image_geometry():
    built = config["domains"]["range_image"]
    trained = config["generator"]["range_image"]
    if (built["height"], built["width"]) != (trained["height"], trained["width"]):
        sys.exit(
            "Invalid configuration: domains.range_image is "
            f"{built['height']}x{built['width']} but generator.range_image is "
            f"{trained['height']}x{trained['width']}; the generator trains on the built images, set both alike."
        )


_check_image_geometry()


# Evaluation helpers (rules/evaluation.smk), after what they read.

EXTRACTORS = f"{DATA}/extractors"
EVAL = config["evaluation"]
METRIC_KIND = {"FRD": "frd", "FRID": "frid", "FSVD": "fsvd", "FPVD": "fpvd", "FPD": "fpd"}
# Settings a stage does not read stay out of its params, so changing them reruns nothing.
TABLES = ("generation_quality", "ablation", "kitti360", "tradeoff", "evidence")


def extractor_weights(*metric_lists):
    """{kind: weights path} of the feature metrics used: the configured official file,
    else the workflow's self-trained checkpoint."""
    kinds = sorted({METRIC_KIND[m] for metrics in metric_lists for m in metrics if m in METRIC_KIND})
    official = EVAL["extractors"]["official_weights"]
    return {k: official[k] or f"{EXTRACTORS}/{k}.pt" for k in kinds}


def weights_args(weights):
    return " ".join(f"--weights {k}={v}" for k, v in weights.items())


# DDIM steps of the distilled student (generator.distillation).
STUDENT_STEPS = student_steps(config["generator"]["distillation"])


def tradeoff_default_sampler():
    """--default-sampler for the sampler study when the generator's own sampler is in its grid."""
    gen = config["generator"]["sampling"]
    grid = config["evaluation"]["tradeoff"]["samplers"]
    return f" --default-sampler {gen['sampler']}:{gen['steps']}" if gen["steps"] in grid.get(gen["sampler"], []) else ""


def sampling_checkpoint(preset):
    """What sample_domain samples: the trained generator, or its distilled student."""
    name = "student.pt" if config["generator"]["sampling"]["student"] else "model.pt"
    return f"{DATA}/generator/{preset}/{name}"


def single_domain_settings(domain):
    """The generator section with the single_domain preset's domain (and optional iterations) set."""
    gen = json.loads(settings("generator", drop=("sampling", "distillation")))
    gen["training"]["single_domain"] = domain
    if EVAL["generation_quality"]["baseline_iterations"]:
        gen["training"]["iterations"] = EVAL["generation_quality"]["baseline_iterations"]
    return json.dumps(gen, sort_keys=True)


def eval_settings(*reads):
    return settings("evaluation", drop=tuple(t for t in TABLES if t not in reads))


# Downstream helpers (rules/downstream.smk), after what they read.

SEG = f"{DATA}/segmentation"
PSEUDO = f"{DATA}/pseudo_labels"
DOWNSTREAM = config["downstream"]
EXPERIMENTS = DOWNSTREAM["experiments"]
CORRUPTIONS = config["domains"]["corrupted"]["corruptions"]
SEVERITIES = config["domains"]["corrupted"]["severities"]


def downstream_settings(*keys):
    """Some top-level keys of the downstream section as one JSON value."""
    return json.dumps({k: DOWNSTREAM[k] for k in keys}, sort_keys=True)


def generator_datasets():
    """The datasets the generator's training domains come from."""
    return sorted({config["domains"][name]["dataset"] for name in DOMAIN_NAMES})


def data_sources(*datasets):
    """{dataset: {root, kind}} of ``datasets`` plus the generator's datasets."""
    return {d: data_source_record(dataset_root(d), is_synthetic(d)) for d in sorted({*datasets, *generator_datasets()})}


def data_source(*datasets):
    """--data-source of a result that uses ``datasets`` and the generator (omnilidar.data_source)."""
    return json.dumps(data_sources(*datasets), sort_keys=True)


# Datasets behind each result target besides the generator's (rules/*.smk pass the same).
RESULT_DATASETS = {
    "semkitti_*pct, semkittic, semanticstf, gda_curve": ("semantickitti",),
    "nusc_beam32_*pct": ("nuscenes",),
    "pi3det_*pct": ("pi3det",),
    "kitti360_generation": ("kitti360",),
    "generation_quality, ablation, tradeoff, generator_evidence": (),
}


def _warn_mixed_data():
    """One warning when results would mix real and synthetic datasets, saying which."""
    mixed = [f"{t} use {describe_sources(data_sources(*ds), roots=False)}"
             for t, ds in RESULT_DATASETS.items() if sources_mixed(data_sources(*ds))]
    if mixed:
        print(f"Warning: results mix real and synthetic (generated by the synthetic world) datasets: "
              f"{'; '.join(mixed)}. Each result lists its datasets and roots in data_source.", file=sys.stderr)


_warn_mixed_data()


def _warn_missing_roots():
    """One line per configured dataset root that does not exist (its index job would fail)."""
    for name, entry in sorted(config["datasets"].items()):
        if entry["root"] is not None and not os.path.isdir(entry["root"]):
            print(f"Warning: datasets.{name}.root {entry['root']} does not exist: every target that reads "
                  f"{name} will fail at its index job (set the root, or null for the synthetic world)", file=sys.stderr)


_warn_missing_roots()


# Domains of a GDA run joined by '+' (only configured names, so gda-vehicle_seed1 is seed 1 of
# gda-vehicle, never a domain called vehicle_seed1).
_DOMAIN_ALTERNATIVES = f"(?:{'|'.join(DOMAIN_NAMES)})"
GDA_DOMAINS_PATTERN = rf"{_DOMAIN_ALTERNATIVES}(?:\+{_DOMAIN_ALTERNATIVES})*"


def gda_domains(w):
    return w.domains.split("+")


def domain_sample_shards(name, scans=None):
    """Sample shards of a domain given by its config key (samples are named by label)."""
    return sample_shards(domain_label(name), scans)


def pseudo_label_shards(name, scans=None):
    """Pseudo-label shard of every sample shard of a domain (same label and shard names)."""
    return [d.replace(f"{DATA}/samples/", f"{PSEUDO}/", 1) for d in domain_sample_shards(name, scans)]


def eval_sets(w):
    """--set NAME=DIR arguments and folders of an evaluation group."""
    if w.evalset == "corrupted":
        return {f"{c}/{s}": f"{CORRUPTED}/{c}/{s}" for c in CORRUPTIONS for s in SEVERITIES}
    if w.evalset in CORRUPTIONS:  # one corruption at every severity
        return {f"{w.evalset}/{s}": f"{CORRUPTED}/{w.evalset}/{s}" for s in SEVERITIES}
    if w.evalset == "weather":
        stf = EXPERIMENTS["semanticstf"]
        if stf["subsets"]:
            return dict(stf["subsets"])
        return {name: f"{CORRUPTED}/{cs}" for name, cs in stf["standin_sets"].items()}
    return {}


def eval_inputs(w):
    sets = eval_sets(w)
    # Real folders given in config are read as they are; corrupted sets are built.
    return [d for d in sets.values() if d.startswith(f"{CORRUPTED}/")]


def run_evaluation(dataset, backbone, pct, augmentation, evalset):
    return f"{SEG}/{dataset}/{backbone}_{pct}pct_{augmentation}.{evalset}.json"


def seed_suffix(k):
    """File-name suffix of a run's k-th seed (k = 0: the configured seed, no suffix)."""
    return "" if k == 0 else f"_seed{config['seed'] + k}"


def comparison(dataset, backbones, pct, domains, evalset, seeds=1):
    """Evaluations of the supervised-only and GDA runs of each backbone, for each of ``seeds`` seeds."""
    gda = "gda-" + "+".join(domains)
    return [run_evaluation(dataset, b, pct, a + seed_suffix(k), evalset)
            for b in backbones for a in ("real", gda) for k in range(seeds)]


def generated_pseudo_labels(domains):
    return [d for name in domains for d in pseudo_label_shards(name)]


GDA_RESULT = (
    "omnilidar gda-result --experiment {params.experiment} --kind {params.kind} --settings {params.settings:q} "
    "--seed {params.seed} --data-source {params.data_source:q} --evaluations {input.evaluations} "
    "--pseudo-labels {input.pseudo} --labeler-evaluation {input.labeler} --out {output.json} "
    "--figure {output.figure} > {log} 2>&1"
)
GDA_RESULT_STANDIN = GDA_RESULT.replace("> {log}", "{params.standin} > {log}")


# GDA curve helpers (downstream.experiments.gda_curve).


def _check_gda_curve():
    curve = config.get("downstream", {}).get("experiments", {}).get("gda_curve")
    if curve and curve["domain"] not in DOMAIN_NAMES:
        sys.exit(
            f"Invalid configuration: downstream.experiments.gda_curve.domain {curve['domain']!r} "
            f"is not a domain (one of: {', '.join(DOMAIN_NAMES)})."
        )


_check_gda_curve()


def curve_counts():
    """Generated-scan counts of the GDA curve, capped by the scans sampled per domain,
    unique and sorted; 0 is the supervised-only run."""
    cap = config["generator"]["sampling"]["scans_per_domain"]
    return sorted({min(int(n), cap) for n in EXPERIMENTS["gda_curve"]["generated_scans"]})


CURVE_SERIES_ROW = {"real_truth": "truth", "real_pseudo": "pseudo"}


def curve_pool_size():
    """Scans of the pool the curve's real series draw their first N from (its largest count)."""
    return max(curve_counts())


def curve_evaluations():
    """Val evaluations of the curve's runs by count: 0 is the supervised-only run that
    results/semkitti_{pct}pct.json compares (reused), N the run on the first N scans (generated,
    and for each real series the first N pool scans)."""
    curve = EXPERIMENTS["gda_curve"]
    runs = ["real" if n == 0 else f"gda{n}-{curve['domain']}" for n in curve_counts()]
    runs += [f"pool{curve_pool_size()}-{CURVE_SERIES_ROW[s]}{n}" for s in curve["real_series"]
             for n in curve_counts() if n > 0]
    return [run_evaluation("semantickitti", curve["backbone"], curve["percent"], r + seed_suffix(k), "val")
            for r in runs for k in range(curve["seeds"])]


def curve_pool_inputs(w):
    """Inputs of a curve run on pool scans: the subset, the pool and, for pseudo, its labels."""
    inputs = {"subset": f"{DATA}/subsets/semantickitti_{w.pct}pct.json", "pool": pool_file(w.pct, w.pool)}
    if w.row == "pseudo":
        inputs["labels"] = pool_labels_dir(w.pct, w.pool)
    return inputs


DECOMPOSITION = EXPERIMENTS["gda_decomposition"]
# N may exceed generator.sampling.scans_per_domain: the study's domains sample the further shards.
DECOMPOSITION_SCANS = DECOMPOSITION["scans"]
WEATHER_STUDY = DECOMPOSITION["weather"]
# Row of the decomposition study -> its run's wildcard (files ..._study-<row><N>_seed<k>.pt); the
# generated row names its domain (gda-<domain>, an attempt gda-<domain>-<attempt>), the simulated
# row of the weather study too (sim-<domain>).
DECOMPOSITION_RUNS = {"supervised_only": "real", "real_truth": "truth", "real_pseudo": "pseudo",
                      "generated": f"gda-{DECOMPOSITION['domain']}", "lasermix": "lasermix",
                      # the pool through the generator's range image and back: true labels, the labeler's
                      "round_trip_truth": f"trip-{DECOMPOSITION['domain']}",
                      "round_trip_pseudo": f"trippseudo-{DECOMPOSITION['domain']}"}
# Kind of study run -> the train-segmentor arguments it adds.
STUDY_FLAGS = {
    "real": "",
    "truth": "--pool {input.pool}",
    "pseudo": "--pool {input.pool} --pool-labels {input.labels}",
    "lasermix": "--pool {input.pool} --pool-labels {input.labels} --lasermix",
    "gda": "--samples {input.samples} --pseudo-labels {input.pseudo} --domains {domain} --max-generated {scans}",
    "sim": "--pool {input.pool}/pool.json --pool-source simulated",
    "trip": "--pool {input.pool}/pool.json --pool-source round_trip",
    "trippseudo": "--pool {input.pool}/pool.json --pool-source round_trip --pool-labels {input.labels}",
}


def study_domains():
    """Domains of the study's generated rows: the main one and the weather study's."""
    return [DECOMPOSITION["domain"], *([WEATHER_STUDY["domain"]] if WEATHER_STUDY["domain"] else [])]


def study_row_pattern():
    """Wildcard pattern of a study run's row."""
    rows = ["real", "truth", "pseudo", "lasermix"]
    rows += [f"gda-{d}-{a}" for d in study_domains() for a in STUDY_VARIANTS]
    rows += [f"gda-{d}" for d in study_domains()]
    rows += [f"sim-{WEATHER_STUDY['domain']}"] if WEATHER_STUDY["domain"] else []
    rows += [f"trip-{DECOMPOSITION['domain']}", f"trippseudo-{DECOMPOSITION['domain']}"]
    return "|".join(rows)


def simulated_pool_dir(domain, pct, scans):
    """The pool's real scans run through a domain's scene (simulate-pool)."""
    return f"{DATA}/subsets/simulated/{domain}_{pct}pct_pool{scans}"


def round_trip_pool_dir(domain, pct, scans):
    """The pool's real scans through the domain's range image and back (round-trip-pool)."""
    return f"{DATA}/subsets/round_trip/{domain}_{pct}pct_pool{scans}"


def round_trip_labels_dir(domain, pct, scans):
    """The labeler's labels of the round-tripped pool (pseudo-label --pool)."""
    return f"{PSEUDO}/pool/round_trip_{domain}_{pct}pct_pool{scans}"


def study_settings(row):
    """The downstream training keys with the study's own overrides (experiments.gda_decomposition.training)
    and, for an attempt's row (gda-<domain>-<name>), the attempt's (its `generator`, `labels` and `labeler`
    keys aside)."""
    from omnilidar.dicts import deep_merge

    merged = deep_merge({k: DOWNSTREAM[k] for k in (*TRAINING_KEYS, "mixing")}, DECOMPOSITION["training"])
    parts = row.split("-")
    if parts[0] == "gda" and len(parts) == 3:
        overrides = {k: v for k, v in STUDY_VARIANTS[parts[2]].items() if k not in ("generator", "labels", "labeler")}
        merged = deep_merge(merged, overrides)
    return json.dumps(merged, sort_keys=True)


# The budget study (downstream.experiments.gda_budget): one generator per training budget, each a
# variant of the decomposition's generated row (gda-<domain>-budget<N>); the budget equal to the
# main generator's iterations is the main generator's row.
BUDGET = EXPERIMENTS["gda_budget"]
MAIN_GENERATOR_ITERATIONS = config["generator"]["training"]["iterations"]
BUDGET_VARIANTS = {f"budget{n}": {"generator": {"training": {"iterations": n}}}
                   for n in BUDGET["iterations"] if n != MAIN_GENERATOR_ITERATIONS}
# Every variant of the generated row: the decomposition's attempts and the budgets.
STUDY_VARIANTS = {**DECOMPOSITION["attempts"], **BUDGET_VARIANTS}
# A run's file names its variant and then its scan count (..._study-gda-<domain>-<name><scans>_seed<s>),
# so a name that is another's plus digits starting 1-9 (robust and robust10) would read as the other
# with more scans.
for _short in STUDY_VARIANTS:
    for _long in STUDY_VARIANTS:
        if _long != _short and _long.startswith(_short) and re.fullmatch(r"[1-9]\d*", _long[len(_short):]):
            sys.exit(f"Invalid configuration: downstream.experiments.gda_decomposition.attempts {_short!r} and "
                     f"{_long!r}: run files name the attempt, then its scan count, so {_long}<scans> also reads as "
                     f"{_short} with more scans; rename one (e.g. {_short}_a).")


def budget_row(iterations):
    """The study row of the generator trained ``iterations`` steps."""
    domain = DECOMPOSITION["domain"]
    return f"gda-{domain}" if iterations == MAIN_GENERATOR_ITERATIONS else f"gda-{domain}-budget{iterations}"


def budget_variant(iterations):
    """The variant name of a budget's generator, samples and labels; None for the main generator."""
    return None if iterations == MAIN_GENERATOR_ITERATIONS else f"budget{iterations}"


# Variants with a `generator` key sample the generated row from their own generator (the
# generator section with those keys laid over it, e.g. a longer run); its samples and their
# pseudo-labels live under attempt-<name>/ beside the main ones, with the same shard layout.
GENERATOR_ATTEMPTS = [name for name, a in STUDY_VARIANTS.items() if "generator" in a]
for _name in GENERATOR_ATTEMPTS:
    _sampling = STUDY_VARIANTS[_name]["generator"].get("sampling", {})
    if {"scans_per_domain", "scans_per_shard"} & set(_sampling):
        sys.exit(f"Invalid configuration: downstream.experiments.gda_decomposition.attempts.{_name}.generator "
                 "may not change sampling.scans_per_domain or scans_per_shard (its samples keep the main shard layout).")


# Variants with `labels: carried` train on their SDEdited scans labelled by carry-labels (each pixel
# keeps its source training scan's true label) instead of by the labeler: what the generator's edits
# cost the student, apart from what they cost the labeler.
ATTEMPT_LABELS = ("labeler", "carried")
for _name, _variant in STUDY_VARIANTS.items():
    if _variant.get("labels", "labeler") not in ATTEMPT_LABELS:
        sys.exit(f"Invalid configuration: downstream.experiments.gda_decomposition.attempts.{_name}.labels is "
                 f"{_variant['labels']!r}; expected one of {', '.join(ATTEMPT_LABELS)}.")
    if _variant.get("labels") == "carried" and _variant.get("generator", {}).get("sampling", {}).get("strength", 1.0) >= 1.0:
        sys.exit(f"Invalid configuration: downstream.experiments.gda_decomposition.attempts.{_name} carries its "
                 "sources' labels, which needs generator.sampling.strength < 1 (fresh samples have no source scan).")
    if _variant.get("generator", {}).get("sampling", {}).get("keep_source") and \
            _variant["generator"]["sampling"].get("strength", 1.0) >= 1.0:
        sys.exit(f"Invalid configuration: downstream.experiments.gda_decomposition.attempts.{_name}.generator."
                 "sampling.keep_source copies channels from each scan's source scan, which needs strength < 1.")
CARRIED_ATTEMPTS = [name for name, a in STUDY_VARIANTS.items() if a.get("labels") == "carried"]
CARRIED = f"{DATA}/carried_labels"


# Variants with a `labeler` key label their generated row with a labeler of their own: the
# downstream.labeler section with those keys laid over it (for example a labeler trained with
# augmentation.range_jitter, robust to the range error of generated scans). Attempts whose labelers
# would be the same share one, made by the first of them: data/labeler/attempt-<owner>.pt (and its
# val scores beside it); the attempt's labels live under attempt-<name>/ like a generator attempt's.
def _attempt_labeler_section(name):
    """downstream.labeler with attempt ``name``'s labeler keys laid over it, validated."""
    from omnilidar.dicts import deep_merge

    merged = deep_merge(DOWNSTREAM["labeler"], STUDY_VARIANTS[name]["labeler"])
    try:
        return validate({"labeler": merged}, "downstream.schema.yaml", source="config")["labeler"]
    except InputError as err:
        sys.exit(f"Invalid configuration: downstream.experiments.gda_decomposition.attempts.{name}.labeler: {err}")


LABELER_SECTIONS = {name: _attempt_labeler_section(name) for name, a in STUDY_VARIANTS.items() if "labeler" in a}
LABELER_ATTEMPTS = list(LABELER_SECTIONS)
LABELER_OWNER = {}
for _name, _section in LABELER_SECTIONS.items():
    if STUDY_VARIANTS[_name].get("labels") == "carried":
        sys.exit(f"Invalid configuration: downstream.experiments.gda_decomposition.attempts.{_name} sets both "
                 "labels: carried and a labeler of its own; carried labels use no labeler.")
    LABELER_OWNER[_name] = next(o for o, other in LABELER_SECTIONS.items() if other == _section)


def labeler_attempt(domain_path):
    """The attempt whose own labeler labels a pseudo-label folder (attempt-<name>/<domain>), else None."""
    name = domain_path.split(os.sep, 1)[0].removeprefix("attempt-")
    return name if domain_path.startswith("attempt-") and name in LABELER_OWNER else None


def attempt_labeler(name, suffix=".pt"):
    """Checkpoint of attempt ``name``'s own labeler (``suffix=".val.json"``: its val scores)."""
    return f"{DATA}/labeler/attempt-{LABELER_OWNER[name]}{suffix}"


def pseudo_label_inputs(w):
    """What labels a pseudo-label shard: the attempt's own labeler where it has one, else the fixed
    labeler; the shard's samples (the main ones for an attempt that changes only the labeler)."""
    name = labeler_attempt(w.domain)
    samples = w.domain if name in GENERATOR_ATTEMPTS or not name else os.path.basename(w.domain)
    return {"labeler": attempt_labeler(name) if name else LABELER, "samples": f"{DATA}/samples/{samples}/shard_{w.shard}"}


def pseudo_label_settings(w):
    """The labeler section behind that shard's labeler, as one JSON value."""
    name = labeler_attempt(w.domain)
    return json.dumps(LABELER_SECTIONS[name] if name else DOWNSTREAM["labeler"], sort_keys=True)


# Of those, the ones that change more than sampling train their own generator; the others (e.g.
# sampling from the distilled student) sample the main generator or its student.
TRAINED_ATTEMPTS = [name for name in GENERATOR_ATTEMPTS if set(STUDY_VARIANTS[name]["generator"]) - {"sampling"}]


def generator_attempt_pattern(trained=True):
    """Wildcard pattern of the attempts that train a generator of their own, or (``trained=False``)
    of every attempt that samples its own scans (none: matches nothing)."""
    names = sorted(set(GENERATOR_OWNER.values())) if trained else GENERATOR_ATTEMPTS
    return "|".join(names) or r"(?!)"


def attempt_checkpoint(attempt):
    """What an attempt samples: its own generator (or that of an attempt that trains the same one),
    or the main one (its student where asked)."""
    if attempt in TRAINED_ATTEMPTS:
        return f"{GENERATOR}/attempt-{GENERATOR_OWNER[attempt]}/model.pt"
    student = STUDY_VARIANTS[attempt]["generator"].get("sampling", {}).get("student", False)
    return f"{GENERATOR}/full/{'student' if student else 'model'}.pt"


def edit_sources(sampling):
    """The domains index, whose training scans sampling starts from when strength < 1 (SDEdit)."""
    return [f"{DATA}/domains/index.json"] if sampling.get("strength", 1.0) < 1.0 else []


def sources_arg(wildcards, input):
    return f"--domains {input.sources[0]} " if input.sources else ""


def attempt_generator_settings(name, drop=()):
    """The generator section with attempt ``name``'s generator keys laid over it, as one JSON value."""
    from omnilidar.dicts import deep_merge

    merged = deep_merge(config["generator"], STUDY_VARIANTS[name]["generator"])
    return json.dumps({k: v for k, v in merged.items() if k not in drop}, sort_keys=True)


def _trained_settings(name):
    return attempt_generator_settings(name, drop=("sampling", "distillation"))


# Attempts whose generators would train identically share one: the first of them trains it (e.g. a
# budget and the SDEdit attempts that sample the same longer-trained generator at other strengths).
GENERATOR_OWNER = {}
for _name in TRAINED_ATTEMPTS:
    GENERATOR_OWNER[_name] = next(o for o in TRAINED_ATTEMPTS if _trained_settings(o) == _trained_settings(_name))


def attempt_dirs(name, dirs, root):
    """The attempt's counterparts of sample or pseudo-label shard directories under ``root``."""
    return [d.replace(f"{root}/", f"{root}/attempt-{name}/", 1) for d in dirs]


def study_flags(w, input):
    """train-segmentor arguments of a study run's row."""
    parts = w.row.split("-")
    return STUDY_FLAGS[parts[0]].format(input=input, scans=w.scans, domain=parts[1] if len(parts) > 1 else "")


def pool_file(pct, scans):
    """N real train scans outside the pct % subset (make-subset --exclude)."""
    return f"{DATA}/subsets/semantickitti_{pct}pct_pool{scans}.json"


def pool_labels_dir(pct, scans):
    """The labeler's labels of that pool (pseudo-label --pool)."""
    return f"{PSEUDO}/pool/semantickitti_{pct}pct_pool{scans}"


def study_run_inputs(w):
    """Inputs of a study run (train_study): the subset, and what its row adds."""
    inputs = {"subset": f"{DATA}/subsets/semantickitti_{w.pct}pct.json"}
    kind, domain, attempt = (w.row.split("-") + [None, None])[:3]
    if kind in ("truth", "pseudo", "lasermix"):
        inputs["pool"] = pool_file(w.pct, w.scans)
    if kind in ("pseudo", "lasermix"):
        inputs["labels"] = pool_labels_dir(w.pct, w.scans)
    if kind == "gda":
        inputs["samples"] = domain_sample_shards(domain, w.scans)
        inputs["pseudo"] = pseudo_label_shards(domain, w.scans)
        if attempt in GENERATOR_ATTEMPTS:
            inputs["samples"] = attempt_dirs(attempt, inputs["samples"], f"{DATA}/samples")
            inputs["pseudo"] = attempt_dirs(attempt, inputs["pseudo"], PSEUDO)
        elif attempt in LABELER_ATTEMPTS:
            inputs["pseudo"] = attempt_dirs(attempt, inputs["pseudo"], PSEUDO)
        if attempt in CARRIED_ATTEMPTS:
            inputs["pseudo"] = [d.replace(f"{DATA}/samples/", f"{CARRIED}/", 1) for d in inputs["samples"]]
    if kind == "sim":
        inputs["pool"] = simulated_pool_dir(domain, w.pct, w.scans)
    if kind in ("trip", "trippseudo"):
        inputs["pool"] = round_trip_pool_dir(domain, w.pct, w.scans)
    if kind == "trippseudo":
        inputs["labels"] = round_trip_labels_dir(domain, w.pct, w.scans)
    return inputs


def heldout_file(pct=None):
    """The decomposition's held-out train scans: whole train sequences that hold no scan of the label
    subset; no pool scan comes from them."""
    pct = DECOMPOSITION["percent"] if pct is None else pct
    return f"{DATA}/subsets/semantickitti_{pct}pct_heldout{DECOMPOSITION['heldout_scans']}.json"


def study_evaluations(rows, evalset, backbones=None):
    """Evaluations (on ``evalset``) of the study runs of ``rows`` for every backbone (default: the
    study's) and seed."""
    d = DECOMPOSITION
    return [run_evaluation("semantickitti", b, d["percent"],
                           f"study-{row}{DECOMPOSITION_SCANS}_seed{config['seed'] + k}", evalset)
            for b in (backbones or d["backbones"]) for row in rows for k in range(d["seeds"])]


def budget_reference_evaluations():
    """The decomposition's supervised-only and pseudo-labelled real rows the budgets are read against."""
    return study_evaluations(["real", "pseudo"], "heldout", [BUDGET["backbone"]])


def budget_run_evaluations():
    """ITERATIONS=EVALUATION of every budget's GDA runs (each seed)."""
    return [f"{n}={path}" for n in BUDGET["iterations"]
            for path in study_evaluations([budget_row(n)], "heldout", [BUDGET["backbone"]])]


def budget_generator(iterations):
    """The generator checkpoint trained ``iterations`` steps."""
    variant = budget_variant(iterations)
    return f"{GENERATOR}/full/model.pt" if variant is None else attempt_checkpoint(variant)


def budget_samples(iterations):
    """The first N samples of the decomposition's domain from that generator (shard folders)."""
    shards = domain_sample_shards(DECOMPOSITION["domain"], DECOMPOSITION_SCANS)
    variant = budget_variant(iterations)
    return shards if variant is None else attempt_dirs(variant, shards, f"{DATA}/samples")


def decomposition_evaluations():
    """Evaluations (val and the held-out train scans) of every row, backbone and seed of the study."""
    return study_evaluations(DECOMPOSITION_RUNS.values(), "heldout")


def weather_evaluations():
    """The weather study's rows on its corrupted sets: the shared real rows, the weather domain's
    generated scans and the domain builder's version of the pool."""
    d = WEATHER_STUDY["domain"]
    rows = ["real", "truth", "pseudo", "lasermix", f"gda-{d}", f"sim-{d}"]
    return study_evaluations(rows, WEATHER_STUDY["corruption"])


def attempt_evaluations(domain, evalset):
    """NAME=evaluation arguments of every attempt's runs (gda-<domain>-<name> rows)."""
    return [f"{name}={path}" for name in DECOMPOSITION["attempts"]
            for path in study_evaluations([f"gda-{domain}-{name}"], evalset)]


def subset_sets_args(w):
    """--subset-set arguments of an evaluation group (the held-out train scans)."""
    return f"--subset-set heldout={heldout_file()}" if w.evalset == "heldout" else ""


# Detection helpers (rules/detection.smk), after what they read.

DET = f"{DATA}/detection"
PSEUDO_BOXES = f"{DATA}/pseudo_boxes"
DET_SECTION = DOWNSTREAM["det"]
PI3DET_EXP = DET_SECTION["experiments"]["pi3det"]
DET_DATA_KEYS = ("device", "platforms", "point_cloud_range", "voxel_size", "voxels", "anchors")
DETECTOR_NAMES = r"voxel_rcnn|pv_rcnn"
PI3DET_PLATFORMS = r"drone|quadruped"


def det_settings(*keys, detector=None):
    """Data keys plus ``keys`` of downstream.det (and one detector's entry) as one JSON value."""
    wanted = {k: DET_SECTION[k] for k in (*DET_DATA_KEYS, *keys)}
    if detector is not None:
        wanted["detectors"] = {detector: DET_SECTION["detectors"][detector]}
    return json.dumps(wanted, sort_keys=True)


def detector_yaml(detector):
    """The detector's yaml as an input path: relative to the workflow unless the working directory has it."""
    return str(workflow_file(DET_SECTION["detectors"][detector]["config"]))


def labeler_checkpoint(platform):
    return DET_SECTION["labeler"]["checkpoint"][platform]


def pseudo_box_shards(platform):
    """Pseudo-box shard of every sample shard of the platform's domain (same label and shard names)."""
    return [d.replace(f"{DATA}/samples/", f"{PSEUDO_BOXES}/", 1) for d in domain_sample_shards(platform)]


def label_platform(label):
    """The platform whose domain's samples carry ``label`` (Drone -> drone)."""
    return {domain_label(p): p for p in ("drone", "quadruped") if p in DOMAIN_NAMES}[label]


# The labeler trains with the schema's augmentation (its settings leave the key out).
_DET_DEFAULT_AUGMENTATION = validate({"det": {}}, "downstream.schema.yaml")["det"]["augmentation"]


def labeler_is_run(platform, detector, pct):
    """Whether the supervised-only run is exactly the labeler's training (same detector, frames,
    schedule, augmentation and seed), so that the labeler's checkpoint stands in for it."""
    lab = DET_SECTION["labeler"]
    return (int(pct) == 100 and not labeler_checkpoint(platform) and lab["detector"] == detector
            and lab["schedule"] == DET_SECTION["schedule"]
            and DET_SECTION["augmentation"] == _DET_DEFAULT_AUGMENTATION)


def det_run(platform, detector, pct, role):
    if role == "real" and labeler_is_run(platform, detector, pct):
        return f"{DET}/{platform}/labeler"
    return f"{DET}/{platform}/{detector}_{pct}pct_{role}"
