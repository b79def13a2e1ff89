# Segmentation GDA stage: label subsets, the fixed labeler, pseudo-labels of the
# generated samples, MinkUNet / SPVCNN trained from scratch (supervised-only and
# GDA), evaluation and the experiment targets.
#
# What each rule sees, so that only what changed reruns:
#   labeler, pseudo-labels      downstream.labeler only (never the generator's settings)
#   supervised-only runs        real subset + training keys (no generator input, no mixing)
#   GDA runs                    + sample shards, pseudo-labels, mixing
#   GDA curve runs              the same, on the first N scans (only the shards holding them)
#   evaluation                  backend, device, evaluation
# Sample shards come from rules/generator.smk (rule sample_domain; common.smk's
# sample_shards(label)); experiments name domains by their config keys.

# SEG, PSEUDO, DOWNSTREAM, EXPERIMENTS, CORRUPTIONS and SEVERITIES are in rules/common.smk,
# whose helpers read them.
SUBSETS = f"{DATA}/subsets"
LABELER = f"{DATA}/labeler/semantickitti.pt"
LABELER_VAL = f"{DATA}/labeler/semantickitti.val.json"  # its own scores, recorded in every GDA result
GDA_CURVE = EXPERIMENTS["gda_curve"]
TRAINING_KEYS = ("backend", "device", "voxel_size", "max_voxels", "max_points", "models", "schedule", "augmentation")




rule make_subset:
    """A label subset: one scan out of every 100/pct of the train split, as a JSON list."""
    input:
        f"{DATA}/index/{{dataset}}.json",
    output:
        f"{SUBSETS}/{{dataset}}_{{pct}}pct.json",
    wildcard_constraints:
        dataset=r"semantickitti|nuscenes",
        pct=r"\d+",
    params:
        split="train",
        code=code("make-subset"),
    log:
        f"logs/downstream/subset_{{dataset}}_{{pct}}pct.log",
    benchmark:
        f"benchmarks/out/downstream/subset_{{dataset}}_{{pct}}pct.tsv"
    conda:
        ENV
    resources:
        **job_resources("make_subset"),
    shell:
        "omnilidar make-subset --index {input} --split {params.split} --percent {wildcards.pct} "
        "--out {output} > {log} 2>&1"


# The fixed labeler's training and an attempt's own (the latter as one job: no segments).
TRAIN_LABELER_SHELL = (
    "omnilidar train-labeler --index {{input.index}} --settings {{params.settings:q}} --seed {{params.seed}} "
    "--work-dir {{params.work_dir}} --threads {{threads}} --out {{output}}{segment} > {{log}} 2>&1"
)


rule train_labeler:
    """The fixed labeler: the configured checkpoint, or trained once on 100 % of the
    real SemanticKITTI train split (independent of the generator)."""
    input:
        index=[] if DOWNSTREAM["labeler"]["checkpoint"] else f"{DATA}/index/semantickitti.json",
        checkpoint=DOWNSTREAM["labeler"]["checkpoint"] or [],
        previous=previous_segment("train_labeler", LABELER),
    output:
        LABELER,
    params:
        settings=settings("downstream", "labeler"),
        seed=config["seed"],
        work_dir="work/labeler",
        segment=segment_flag,
        code=code("train-labeler"),
    log:
        "logs/downstream/labeler.log",
    benchmark:
        "benchmarks/out/downstream/labeler.tsv"
    conda:
        ENV
    threads: 1
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("train_labeler"),
    shell:
        TRAIN_LABELER_SHELL.format(segment=" {params.segment}")


# A training longer than its partition's time limit: the segment jobs of its chain (resources.smk).
use rule train_labeler as train_labeler_segment with:
    output:
        segment_output(LABELER),
    log:
        "logs/downstream/labeler.part{part}of{parts}.log",
    benchmark:
        "benchmarks/out/downstream/labeler.part{part}of{parts}.tsv"


rule train_labeler_attempt:
    """The labeler of a decomposition attempt that has one of its own (attempts.<name>.labeler laid
    over downstream.labeler), trained like the fixed one on 100 % of the real train split."""
    input:
        index=f"{DATA}/index/semantickitti.json",
    output:
        f"{DATA}/labeler/attempt-{{attempt}}.pt",
    wildcard_constraints:
        attempt="|".join(sorted(set(LABELER_OWNER.values()))) or r"(?!)",
    params:
        settings=lambda w: json.dumps(LABELER_SECTIONS[w.attempt], sort_keys=True),
        seed=config["seed"],
        work_dir=lambda w: f"work/labeler/attempt-{w.attempt}",
        code=code("train-labeler"),
    log:
        "logs/downstream/labeler_attempt-{attempt}.log",
    benchmark:
        "benchmarks/out/downstream/labeler_attempt-{attempt}.tsv"
    conda:
        ENV
    threads: 1
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("train_labeler"),
    shell:
        TRAIN_LABELER_SHELL.format(segment="")


rule evaluate_labeler:
    """The labeler's own per-class IoU and mIoU on the SemanticKITTI val split (the quality of
    every pseudo-label a GDA run learns from)."""
    input:
        checkpoint=LABELER,
        index=f"{DATA}/index/semantickitti.json",
    output:
        LABELER_VAL,
    params:
        settings=downstream_settings("backend", "device", "evaluation"),
        code=code("evaluate-segmentor"),
    log:
        "logs/downstream/evaluate/labeler.val.log",
    benchmark:
        "benchmarks/out/downstream/evaluate/labeler.val.tsv"
    conda:
        ENV
    threads: 1
    resources:
        **job_resources("evaluate_segmentor"),
    shell:
        "omnilidar evaluate-segmentor --checkpoint {input.checkpoint} --index {input.index} --split val "
        "--settings {params.settings:q} --threads {threads} --out {output} > {log} 2>&1"


use rule evaluate_labeler as evaluate_labeler_attempt with:
    input:
        checkpoint=f"{DATA}/labeler/attempt-{{attempt}}.pt",
        index=f"{DATA}/index/semantickitti.json",
    output:
        f"{DATA}/labeler/attempt-{{attempt}}.val.json",
    log:
        "logs/downstream/evaluate/labeler_attempt-{attempt}.val.log",
    benchmark:
        "benchmarks/out/downstream/evaluate/labeler_attempt-{attempt}.val.tsv"


rule pseudo_label:
    """Pseudo-labels (raw SemanticKITTI ids) for one shard of generated scans (an attempt's labeler
    where it has one of its own)."""
    input:
        unpack(pseudo_label_inputs),
    output:
        directory(f"{PSEUDO}/{{domain}}/shard_{{shard}}"),
    wildcard_constraints:
        shard=r"\d+",
    params:
        settings=pseudo_label_settings,
        code=code("pseudo-label"),
    log:
        f"logs/downstream/pseudo_labels/{{domain}}_{{shard}}.log",
    benchmark:
        f"benchmarks/out/downstream/pseudo_labels/{{domain}}_{{shard}}.tsv"
    conda:
        ENV
    threads: 1
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("pseudo_label"),
    shell:
        "omnilidar pseudo-label --labeler {input.labeler} --samples {input.samples} "
        "--settings {params.settings:q} --threads {threads} --out {output} > {log} 2>&1"


SUPERVISED_RUN = f"{SEG}/{{dataset}}/{{backbone}}_{{pct}}pct_real.pt"
GDA_RUN = f"{SEG}/{{dataset}}/{{backbone}}_{{pct}}pct_gda-{{domains}}.pt"
CURVE_RUN = f"{SEG}/{{dataset}}/{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}.pt"
POOL_RUN = f"{SEG}/semantickitti/{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}.pt"
STUDY_RUN = f"{SEG}/semantickitti/{{backbone}}_{{pct}}pct_study-{{row}}{{scans}}_seed{{seed}}.pt"


rule train_supervised:
    """Supervised-only run: the real label subset alone, from scratch."""
    input:
        subset=f"{SUBSETS}/{{dataset}}_{{pct}}pct.json",
        previous=previous_segment("train_supervised", SUPERVISED_RUN),
    output:
        SUPERVISED_RUN,
    wildcard_constraints:
        dataset=r"semantickitti|nuscenes",
        backbone=r"minkunet|spvcnn",
        pct=r"\d+",
    params:
        settings=downstream_settings(*TRAINING_KEYS),
        seed=config["seed"],
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        code=code("train-segmentor"),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_real.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_real.tsv"
    conda:
        ENV
    priority: training_priority
    threads: 1
    resources:
        **job_resources("train_supervised"),
    shell:
        "omnilidar train-segmentor --backbone {wildcards.backbone} --subset {input.subset} "
        "--settings {params.settings:q} --seed {params.seed} --work-dir {params.work_dir} "
        "--threads {threads} --out {output} {params.segment} > {log} 2>&1"


use rule train_supervised as train_supervised_segment with:
    output:
        segment_output(SUPERVISED_RUN),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_real.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_real.part{{part}}of{{parts}}.tsv"


rule train_gda:
    """GDA run: the real label subset plus the pseudo-labelled generated scans of the
    domains (joined by '+'), from scratch; the mixing is configured and recorded."""
    input:
        subset=f"{SUBSETS}/{{dataset}}_{{pct}}pct.json",
        samples=lambda w: [d for name in gda_domains(w) for d in domain_sample_shards(name)],
        pseudo=lambda w: generated_pseudo_labels(gda_domains(w)),
        previous=previous_segment("train_gda", GDA_RUN),
    output:
        GDA_RUN,
    wildcard_constraints:
        dataset=r"semantickitti|nuscenes",
        backbone=r"minkunet|spvcnn",
        pct=r"\d+",
        domains=GDA_DOMAINS_PATTERN,
    params:
        settings=downstream_settings(*TRAINING_KEYS, "mixing"),
        seed=config["seed"],
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        domains=lambda w: " ".join(gda_domains(w)),
        code=code("train-segmentor"),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda-{{domains}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda-{{domains}}.tsv"
    conda:
        ENV
    priority: training_priority
    threads: 1
    resources:
        **job_resources("train_gda"),
    shell:
        "omnilidar train-segmentor --backbone {wildcards.backbone} --subset {input.subset} "
        "--settings {params.settings:q} --seed {params.seed} --work-dir {params.work_dir} "
        "--threads {threads} --out {output} --samples {input.samples} --pseudo-labels {input.pseudo} "
        "--domains {params.domains} {params.segment} > {log} 2>&1"


use rule train_gda as train_gda_segment with:
    output:
        segment_output(GDA_RUN),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda-{{domains}}.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda-{{domains}}.part{{part}}of{{parts}}.tsv"


# Extra seeds of a run (downstream.experiments.<name>.seeds): the same job with seed
# seed + k, its files ending in _seed<seed + k>.
use rule train_supervised as train_supervised_seed with:
    output:
        f"{SEG}/{{dataset}}/{{backbone}}_{{pct}}pct_real_seed{{seed}}.pt",
    wildcard_constraints:
        dataset=r"semantickitti|nuscenes",
        backbone=r"minkunet|spvcnn",
        pct=r"\d+",
        seed=r"\d+",
    params:
        settings=downstream_settings(*TRAINING_KEYS),
        seed=lambda w: int(w.seed),
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        code=code("train-segmentor"),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_real_seed{{seed}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_real_seed{{seed}}.tsv"


use rule train_supervised_seed as train_supervised_seed_segment with:
    output:
        segment_output(f"{SEG}/{{dataset}}/{{backbone}}_{{pct}}pct_real_seed{{seed}}.pt"),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_real_seed{{seed}}.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_real_seed{{seed}}.part{{part}}of{{parts}}.tsv"


use rule train_gda as train_gda_seed with:
    output:
        f"{SEG}/{{dataset}}/{{backbone}}_{{pct}}pct_gda-{{domains}}_seed{{seed}}.pt",
    wildcard_constraints:
        dataset=r"semantickitti|nuscenes",
        backbone=r"minkunet|spvcnn",
        pct=r"\d+",
        domains=GDA_DOMAINS_PATTERN,
        seed=r"\d+",
    params:
        settings=downstream_settings(*TRAINING_KEYS, "mixing"),
        seed=lambda w: int(w.seed),
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        domains=lambda w: " ".join(gda_domains(w)),
        code=code("train-segmentor"),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda-{{domains}}_seed{{seed}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda-{{domains}}_seed{{seed}}.tsv"


use rule train_gda_seed as train_gda_seed_segment with:
    output:
        segment_output(f"{SEG}/{{dataset}}/{{backbone}}_{{pct}}pct_gda-{{domains}}_seed{{seed}}.pt"),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda-{{domains}}_seed{{seed}}.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda-{{domains}}_seed{{seed}}.part{{part}}of{{parts}}.tsv"


ruleorder: train_gda_seed > train_gda
ruleorder: train_gda_seed_segment > train_gda_segment


rule train_gda_curve:
    """One point of the GDA curve: the real label subset plus the first N generated scans
    (wildcard scans) of one domain (sample shards in order, scans in name order), from
    scratch. Only the shards holding those scans are inputs; the checkpoint records N."""
    input:
        subset=f"{SUBSETS}/{{dataset}}_{{pct}}pct.json",
        samples=lambda w: domain_sample_shards(w.domain, w.scans),
        pseudo=lambda w: pseudo_label_shards(w.domain, w.scans),
        previous=previous_segment("train_gda_curve", CURVE_RUN),
    output:
        CURVE_RUN,
    wildcard_constraints:
        dataset=r"semantickitti|nuscenes",
        backbone=r"minkunet|spvcnn",
        pct=r"\d+",
        scans=r"[1-9]\d*",
        domain="|".join(DOMAIN_NAMES),
    params:
        settings=downstream_settings(*TRAINING_KEYS, "mixing"),
        seed=config["seed"],
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        code=code("train-segmentor"),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}.tsv"
    conda:
        ENV
    priority: training_priority
    threads: 1
    resources:
        **job_resources("train_gda_curve"),
    shell:
        "omnilidar train-segmentor --backbone {wildcards.backbone} --subset {input.subset} "
        "--settings {params.settings:q} --seed {params.seed} --work-dir {params.work_dir} "
        "--threads {threads} --out {output} --samples {input.samples} --pseudo-labels {input.pseudo} "
        "--domains {wildcards.domain} --max-generated {wildcards.scans} {params.segment} > {log} 2>&1"


use rule train_gda_curve as train_gda_curve_segment with:
    output:
        segment_output(CURVE_RUN),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}.part{{part}}of{{parts}}.tsv"


use rule train_gda_curve as train_gda_curve_seed with:
    output:
        f"{SEG}/{{dataset}}/{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}_seed{{seed}}.pt",
    wildcard_constraints:
        dataset=r"semantickitti|nuscenes",
        backbone=r"minkunet|spvcnn",
        pct=r"\d+",
        scans=r"[1-9]\d*",
        domain="|".join(DOMAIN_NAMES),
        seed=r"\d+",
    params:
        settings=downstream_settings(*TRAINING_KEYS, "mixing"),
        seed=lambda w: int(w.seed),
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        code=code("train-segmentor"),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}_seed{{seed}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}_seed{{seed}}.tsv"


use rule train_gda_curve_seed as train_gda_curve_seed_segment with:
    output:
        segment_output(f"{SEG}/{{dataset}}/{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}_seed{{seed}}.pt"),
    log:
        f"logs/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}_seed{{seed}}.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/{{dataset}}_{{backbone}}_{{pct}}pct_gda{{scans}}-{{domain}}_seed{{seed}}.part{{part}}of{{parts}}.tsv"


rule train_curve_pool:
    """A point of the GDA curve's real series: the real label subset plus the first N scans of the
    real pool (P scans outside the subset) with their true labels (truth) or the labeler's (pseudo)."""
    input:
        unpack(curve_pool_inputs),
        previous=previous_segment("train_curve_pool", POOL_RUN),
    output:
        POOL_RUN,
    wildcard_constraints:
        backbone=r"minkunet|spvcnn",
        pct=r"\d+",
        pool=r"[1-9]\d*",
        row=r"truth|pseudo",
        scans=r"[1-9]\d*",
    params:
        settings=downstream_settings(*TRAINING_KEYS, "mixing"),
        seed=config["seed"],
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        labels=lambda w, input: f"--pool-labels {input.labels}" if w.row == "pseudo" else "",
        code=code("train-segmentor"),
    log:
        f"logs/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}.tsv"
    conda:
        ENV
    priority: training_priority
    threads: 1
    resources:
        **job_resources("train_curve_pool"),
    shell:
        "omnilidar train-segmentor --backbone {wildcards.backbone} --subset {input.subset} "
        "--settings {params.settings:q} --seed {params.seed} --work-dir {params.work_dir} "
        "--threads {threads} --out {output} --pool {input.pool} {params.labels} --max-pool {wildcards.scans} "
        "{params.segment} > {log} 2>&1"


use rule train_curve_pool as train_curve_pool_segment with:
    output:
        segment_output(POOL_RUN),
    log:
        f"logs/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}.part{{part}}of{{parts}}.tsv"


use rule train_curve_pool as train_curve_pool_seed with:
    output:
        f"{SEG}/semantickitti/{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}_seed{{seed}}.pt",
    wildcard_constraints:
        backbone=r"minkunet|spvcnn",
        pct=r"\d+",
        pool=r"[1-9]\d*",
        row=r"truth|pseudo",
        scans=r"[1-9]\d*",
        seed=r"\d+",
    params:
        settings=downstream_settings(*TRAINING_KEYS, "mixing"),
        seed=lambda w: int(w.seed),
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        labels=lambda w, input: f"--pool-labels {input.labels}" if w.row == "pseudo" else "",
        code=code("train-segmentor"),
    log:
        f"logs/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}_seed{{seed}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}_seed{{seed}}.tsv"


use rule train_curve_pool_seed as train_curve_pool_seed_segment with:
    output:
        segment_output(f"{SEG}/semantickitti/{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}_seed{{seed}}.pt"),
    log:
        f"logs/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}_seed{{seed}}.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_pool{{pool}}-{{row}}{{scans}}_seed{{seed}}.part{{part}}of{{parts}}.tsv"


ruleorder: train_curve_pool_seed > train_curve_pool
ruleorder: train_curve_pool_seed_segment > train_curve_pool_segment


rule evaluate_segmentor:
    """Per-class IoU, mIoU (semantic-kitti-api and nanmean) and accuracy of one run on the
    official val split (val), plus the corrupted sets (corrupted) or weather subsets (weather)."""
    input:
        checkpoint=f"{SEG}/{{dataset}}/{{run}}.pt",
        index=f"{DATA}/index/{{dataset}}.json",
        sets=eval_inputs,
        heldout=lambda w: [heldout_file()] if w.evalset == "heldout" else [],
    output:
        f"{SEG}/{{dataset}}/{{run}}.{{evalset}}.json",
    wildcard_constraints:
        dataset=r"semantickitti|nuscenes",
        run=r"(minkunet|spvcnn)_\d+pct_[a-z0-9_+\-]+",
        evalset=r"val|heldout|corrupted|weather|" + "|".join(CORRUPTIONS),
    params:
        settings=downstream_settings("backend", "device", "evaluation"),
        sets=lambda w: " ".join([*(f"--set {n}={d}" for n, d in eval_sets(w).items()), subset_sets_args(w)]).strip(),
        code=code("evaluate-segmentor"),
    log:
        f"logs/downstream/evaluate/{{dataset}}_{{run}}.{{evalset}}.log",
    benchmark:
        f"benchmarks/out/downstream/evaluate/{{dataset}}_{{run}}.{{evalset}}.tsv"
    conda:
        ENV
    threads: 1
    resources:
        **job_resources("evaluate_segmentor"),
    shell:
        "omnilidar evaluate-segmentor --checkpoint {input.checkpoint} --index {input.index} --split val "
        "{params.sets} --settings {params.settings:q} --threads {threads} --out {output} > {log} 2>&1"


rule semkitti_result:
    """MinkUNet and SPVCNN on a SemanticKITTI label subset: supervised-only vs GDA."""
    input:
        evaluations=lambda w: comparison("semantickitti", EXPERIMENTS["semkitti"]["backbones"], w.pct,
                                         [EXPERIMENTS["semkitti"]["domain"]], "val", EXPERIMENTS["semkitti"]["seeds"]),
        pseudo=generated_pseudo_labels([EXPERIMENTS["semkitti"]["domain"]]),
        labeler=LABELER_VAL,
    output:
        json="results/semkitti_{pct}pct.json",
        table="results/tables/semkitti_{pct}pct.html",
        figure="results/figures/semkitti_{pct}pct.png",
    wildcard_constraints:
        pct=r"\d+",
    params:
        experiment=lambda w: f"semkitti_{w.pct}pct",
        kind="semkitti",
        settings=settings("downstream", drop=("det",)),
        seed=config["seed"],
        data_source=data_source("semantickitti"),
        code=result_code("gda-result"),
    log:
        "logs/downstream/semkitti_{pct}pct.log",
    benchmark:
        "benchmarks/out/downstream/semkitti_{pct}pct.tsv"
    conda:
        ENV
    resources:
        **job_resources("gda_result"),
    shell:
        with_table(GDA_RESULT)


rule semkittic_result:
    """Robustness on the corrupted val sets: mCE and mRR with and without GDA."""
    input:
        evaluations=comparison("semantickitti", [EXPERIMENTS["semkittic"]["backbone"]],
                               EXPERIMENTS["semkittic"]["percent"], EXPERIMENTS["semkittic"]["domains"], "corrupted"),
        pseudo=generated_pseudo_labels(EXPERIMENTS["semkittic"]["domains"]),
        labeler=LABELER_VAL,
    output:
        json="results/semkittic.json",
        table="results/tables/semkittic.html",
        figure="results/figures/semkittic.png",
    params:
        experiment="semkittic",
        kind="semkittic",
        settings=settings("downstream", drop=("det",)),
        seed=config["seed"],
        data_source=data_source("semantickitti"),
        code=result_code("gda-result"),
    log:
        "logs/downstream/semkittic.log",
    benchmark:
        "benchmarks/out/downstream/semkittic.tsv"
    conda:
        ENV
    resources:
        **job_resources("gda_result"),
    shell:
        with_table(GDA_RESULT)


rule nusc_beam32_result:
    """Beam-32 samples augmenting a nuScenes label subset (16 lidarseg classes)."""
    input:
        evaluations=lambda w: comparison("nuscenes", EXPERIMENTS["nusc_beam32"]["backbones"], w.pct,
                                         [EXPERIMENTS["nusc_beam32"]["domain"]], "val", EXPERIMENTS["nusc_beam32"]["seeds"]),
        pseudo=generated_pseudo_labels([EXPERIMENTS["nusc_beam32"]["domain"]]),
        labeler=LABELER_VAL,
    output:
        json="results/nusc_beam32_{pct}pct.json",
        table="results/tables/nusc_beam32_{pct}pct.html",
        figure="results/figures/nusc_beam32_{pct}pct.png",
    wildcard_constraints:
        pct=r"\d+",
    params:
        experiment=lambda w: f"nusc_beam32_{w.pct}pct",
        kind="nusc_beam32",
        settings=settings("downstream", drop=("det",)),
        seed=config["seed"],
        data_source=data_source("nuscenes"),
        code=result_code("gda-result"),
    log:
        "logs/downstream/nusc_beam32_{pct}pct.log",
    benchmark:
        "benchmarks/out/downstream/nusc_beam32_{pct}pct.tsv"
    conda:
        ENV
    resources:
        **job_resources("gda_result"),
    shell:
        with_table(GDA_RESULT)


rule semanticstf_result:
    """Fog, snow and rain samples augmenting the full real set, per weather subset
    (a synthetic-weather stand-in unless SemanticSTF subsets are configured)."""
    input:
        evaluations=comparison("semantickitti", [EXPERIMENTS["semanticstf"]["backbone"]], 100,
                               EXPERIMENTS["semanticstf"]["domains"], "weather"),
        pseudo=generated_pseudo_labels(EXPERIMENTS["semanticstf"]["domains"]),
        labeler=LABELER_VAL,
    output:
        json="results/semanticstf.json",
        table="results/tables/semanticstf.html",
        figure="results/figures/semanticstf.png",
    params:
        experiment="semanticstf",
        kind="semanticstf",
        settings=settings("downstream", drop=("det",)),
        seed=config["seed"],
        data_source=data_source("semantickitti"),
        standin="" if EXPERIMENTS["semanticstf"]["subsets"] else "--standin",
        code=result_code("gda-result"),
    log:
        "logs/downstream/semanticstf.log",
    benchmark:
        "benchmarks/out/downstream/semanticstf.tsv"
    conda:
        ENV
    resources:
        **job_resources("gda_result"),
    shell:
        with_table(GDA_RESULT_STANDIN)


rule gda_curve:
    """Val mIoU of one backbone on one label subset against the number of generated scans
    (0 = the supervised-only run, reused), with what each point cost: its training seconds,
    and sampling and pseudo-labelling seconds per generated scan as measured on the shards."""
    input:
        evaluations=curve_evaluations(),
        samples=domain_sample_shards(GDA_CURVE["domain"], max(curve_counts())),
        pseudo=pseudo_label_shards(GDA_CURVE["domain"], max(curve_counts())),
        labeler=LABELER_VAL,
    output:
        json="results/gda_curve.json",
        table="results/tables/gda_curve.html",
        figure="results/figures/gda_curve.png",
    params:
        settings=settings("downstream", drop=("det",)),
        seed=config["seed"],
        data_source=data_source("semantickitti"),
        code=result_code("gda-curve"),
    log:
        "logs/downstream/gda_curve.log",
    benchmark:
        "benchmarks/out/downstream/gda_curve.tsv"
    conda:
        ENV
    resources:
        **job_resources("gda_curve"),
    shell:
        with_table(
            "omnilidar gda-curve --evaluations {input.evaluations} --samples {input.samples} "
            "--pseudo-labels {input.pseudo} --labeler-evaluation {input.labeler} "
            "--settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
            "--out {output.json} --figure {output.figure} > {log} 2>&1"
        )


rule make_pool:
    """The decomposition study's pool: N real train scans outside a label subset and the held-out
    sequences, evenly spread."""
    input:
        index=f"{DATA}/index/semantickitti.json",
        subset=f"{SUBSETS}/semantickitti_{{pct}}pct.json",
        heldout=lambda w: heldout_file(w.pct),
    output:
        pool_file("{pct}", "{scans}"),
    wildcard_constraints:
        pct=r"\d+",
        scans=r"[1-9]\d*",
    params:
        code=code("make-subset"),
    log:
        "logs/downstream/subset_semantickitti_{pct}pct_pool{scans}.log",
    conda:
        ENV
    resources:
        **job_resources("make_subset"),
    shell:
        "omnilidar make-subset --index {input.index} --exclude {input.subset} --heldout {input.heldout} "
        "--count {wildcards.scans} --out {output} > {log} 2>&1"


rule make_heldout:
    """The decomposition's held-out train scans (whole sequences without a subset scan, never in a
    pool): where its regime is checked, never on val."""
    input:
        index=f"{DATA}/index/semantickitti.json",
        subset=f"{SUBSETS}/semantickitti_{{pct}}pct.json",
    output:
        f"{SUBSETS}/semantickitti_{{pct}}pct_heldout{{scans}}.json",
    wildcard_constraints:
        pct=r"\d+",
        scans=r"[1-9]\d*",
    params:
        code=code("make-subset"),
    log:
        "logs/downstream/subset_semantickitti_{pct}pct_heldout{scans}.log",
    conda:
        ENV
    resources:
        **job_resources("make_subset"),
    shell:
        "omnilidar make-subset --index {input.index} --exclude {input.subset} --whole-sequences "
        "--count {wildcards.scans} --out {output} > {log} 2>&1"


rule pseudo_label_pool:
    """The labeler's labels of a pool's real scans, with their accuracy against the true labels."""
    input:
        labeler=LABELER,
        pool=pool_file("{pct}", "{scans}"),
    output:
        directory(pool_labels_dir("{pct}", "{scans}")),
    wildcard_constraints:
        pct=r"\d+",
        scans=r"[1-9]\d*",
    params:
        settings=settings("downstream", "labeler"),
        code=code("pseudo-label"),
    log:
        "logs/downstream/pseudo_labels/pool_{pct}pct_{scans}.log",
    conda:
        ENV
    threads: 1
    resources:
        **job_resources("pseudo_label"),
    shell:
        "omnilidar pseudo-label --labeler {input.labeler} --pool {input.pool} "
        "--settings {params.settings:q} --threads {threads} --out {output} > {log} 2>&1"


rule train_study:
    """One run of the decomposition study, on its own schedule (experiments.gda_decomposition.training
    over the downstream training keys): the real subset plus N scans of one row - nothing (real),
    pool scans with true labels (truth) or the labeler's (pseudo), LaserMix-ed pool scans (lasermix),
    or the first N generated scans of the domain (gda)."""
    input:
        unpack(study_run_inputs),
        previous=previous_segment("train_study", STUDY_RUN),
    output:
        STUDY_RUN,
    wildcard_constraints:
        backbone=r"minkunet|spvcnn",
        pct=r"\d+",
        row=study_row_pattern(),
        scans=r"[1-9]\d*",
        seed=r"\d+",
    params:
        settings=lambda w: study_settings(w.row),
        seed=lambda w: int(w.seed),
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        flags=study_flags,
        code=code("train-segmentor"),
    log:
        f"logs/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_study-{{row}}{{scans}}_seed{{seed}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_study-{{row}}{{scans}}_seed{{seed}}.tsv"
    conda:
        ENV
    priority: training_priority
    threads: 1
    resources:
        **job_resources("train_study"),
    shell:
        "omnilidar train-segmentor --backbone {wildcards.backbone} --subset {input.subset} "
        "--settings {params.settings:q} --seed {params.seed} --work-dir {params.work_dir} "
        "--threads {threads} --out {output} {params.flags} {params.segment} > {log} 2>&1"


use rule train_study as train_study_segment with:
    output:
        segment_output(STUDY_RUN),
    log:
        f"logs/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_study-{{row}}{{scans}}_seed{{seed}}.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/downstream/train/semantickitti_{{backbone}}_{{pct}}pct_study-{{row}}{{scans}}_seed{{seed}}.part{{part}}of{{parts}}.tsv"


rule gda_decomposition:
    """Where GDA's effect is won or lost: supervised-only, + real scans with true labels, + the same
    with the labeler's labels, + generated scans, + LaserMix, per backbone over several seeds."""
    input:
        evaluations=decomposition_evaluations(),
        attempts=[a.split("=", 1)[1] for a in attempt_evaluations(DECOMPOSITION["domain"], "val")],
        pool_labels=pool_labels_dir(DECOMPOSITION["percent"], DECOMPOSITION_SCANS),
        labeler=LABELER_VAL,
        attempt_labelers=[attempt_labeler(a, ".val.json") for a in LABELER_ATTEMPTS],
    output:
        json="results/gda_decomposition.json",
        table="results/tables/gda_decomposition.html",
        figure="results/figures/gda_decomposition.png",
    params:
        settings=settings("downstream", drop=("det",)),
        seed=config["seed"],
        data_source=data_source("semantickitti"),
        attempts=" ".join(f"--attempt {a}" for a in attempt_evaluations(DECOMPOSITION["domain"], "val")),
        attempt_labelers=" ".join(f"--attempt-labeler {a}={attempt_labeler(a, '.val.json')}" for a in LABELER_ATTEMPTS),
        generator_iterations=MAIN_GENERATOR_ITERATIONS,
        code=result_code("gda-decomposition"),
    log:
        "logs/downstream/gda_decomposition.log",
    benchmark:
        "benchmarks/out/downstream/gda_decomposition.tsv"
    conda:
        ENV
    resources:
        **job_resources("gda_result"),
    shell:
        with_table(
            "omnilidar gda-decomposition --evaluations {input.evaluations} {params.attempts} "
            "--pool-labels {input.pool_labels} --generator-iterations {params.generator_iterations} "
            "--labeler-evaluation {input.labeler} {params.attempt_labelers} --settings {params.settings:q} --seed {params.seed} "
            "--data-source {params.data_source:q} --out {output.json} --figure {output.figure} > {log} 2>&1"
        )


rule simulate_pool:
    """The decomposition pool's real scans run through a domain's scene, labels carried (the
    physically simulated augmentation a generator must beat)."""
    input:
        index=f"{DATA}/index/semantickitti.json",
        pool=pool_file("{pct}", "{scans}"),
    output:
        directory(simulated_pool_dir("{domain}", "{pct}", "{scans}")),
    wildcard_constraints:
        domain="|".join(DOMAIN_NAMES),
        pct=r"\d+",
        scans=r"[1-9]\d*",
    params:
        settings=lambda w: domain_settings(w.domain),
        seed=config["seed"],
        code=lambda w: code("simulate-pool", exclude=tuple(
            f"omnilidar.domains.effects.{m}" for m in EFFECT_MODULES
            if m not in {e["name"] for e in config["domains"][w.domain]["effects"]})),
    log:
        "logs/downstream/simulated_pool_{domain}_{pct}pct_{scans}.log",
    conda:
        ENV
    resources:
        **job_resources("simulate_pool"),
    shell:
        "omnilidar simulate-pool {wildcards.domain} --index {input.index} --pool {input.pool} "
        "--settings {params.settings:q} --seed {params.seed} --out {output} > {log} 2>&1"


BUDGET_WEIGHTS = extractor_weights(BUDGET["metrics"])


rule budget_quality:
    """One budget's samples against the held-out real scans (FRD, JSD, MMD)."""
    input:
        subset=heldout_file(),
        samples=lambda w: budget_samples(int(w.iterations)),
        weights=list(BUDGET_WEIGHTS.values()),
    output:
        f"{DATA}/budget/quality_{{iterations}}.json",
    wildcard_constraints:
        iterations=r"\d+",
    params:
        range_image=json.dumps(config["generator"]["range_image"], sort_keys=True),
        metrics=" ".join(BUDGET["metrics"]),
        scans=min(BUDGET["quality_scans"], DECOMPOSITION_SCANS, DECOMPOSITION["heldout_scans"]),
        weights=weights_args(BUDGET_WEIGHTS),
        code=code("sample-quality"),
    log:
        "logs/downstream/budget_quality_{iterations}.log",
    conda:
        ENV
    resources:
        **job_resources("gda_result"),
    shell:
        "omnilidar sample-quality --subset {input.subset} --samples {input.samples} --scans {params.scans} "
        "--metrics {params.metrics} {params.weights} --range-image {params.range_image:q} "
        "--out {output} > {log} 2>&1"


rule gda_budget:
    """What GDA gains for the generator's training compute: one generator per budget, its samples'
    quality, and the GDA gain over supervised-only seed by seed, beside pseudo-labelled real scans."""
    input:
        evaluations=budget_reference_evaluations(),
        runs=[pair.split("=", 1)[1] for pair in budget_run_evaluations()],
        generators=[budget_generator(n) for n in BUDGET["iterations"]],
        quality=expand(f"{DATA}/budget/quality_{{n}}.json", n=BUDGET["iterations"]),
        labeler=LABELER_VAL,
    output:
        json="results/gda_budget.json",
        table="results/tables/gda_budget.html",
        figure="results/figures/gda_budget.png",
    params:
        settings=settings("downstream", drop=("det",)),
        seed=config["seed"],
        data_source=data_source("semantickitti"),
        budgets=" ".join(f"--budget {n}={budget_generator(n)}={DATA}/budget/quality_{n}.json"
                         for n in BUDGET["iterations"]),
        runs=" ".join(f"--run {pair}" for pair in budget_run_evaluations()),
        code=result_code("gda-budget"),
    log:
        "logs/downstream/gda_budget.log",
    benchmark:
        "benchmarks/out/downstream/gda_budget.tsv"
    conda:
        ENV
    resources:
        **job_resources("gda_result"),
    shell:
        with_table(
            "omnilidar gda-budget --evaluations {input.evaluations} {params.budgets} {params.runs} "
            "--labeler-evaluation {input.labeler} --settings {params.settings:q} --seed {params.seed} "
            "--data-source {params.data_source:q} --out {output.json} --figure {output.figure} > {log} 2>&1"
        )


rule round_trip_pool:
    """The decomposition pool's real scans through the domain's range image and back, true labels
    carried: what a perfect generator of this image size would give (the resolution link)."""
    input:
        index=f"{DATA}/index/semantickitti.json",
        pool=pool_file("{pct}", "{scans}"),
    output:
        directory(round_trip_pool_dir("{domain}", "{pct}", "{scans}")),
    wildcard_constraints:
        domain="|".join(DOMAIN_NAMES),
        pct=r"\d+",
        scans=r"[1-9]\d*",
    params:
        settings=lambda w: domain_settings(w.domain),
        code=code("round-trip-pool"),
    log:
        "logs/downstream/round_trip_pool_{domain}_{pct}pct_{scans}.log",
    conda:
        ENV
    resources:
        **job_resources("simulate_pool"),
    shell:
        "omnilidar round-trip-pool {wildcards.domain} --index {input.index} --pool {input.pool} "
        "--settings {params.settings:q} --out {output} > {log} 2>&1"


rule carry_labels:
    """True labels for an attempt's SDEdited scans (sampling.strength < 1): each pixel keeps its
    source training scan's label, the labeler-free counterpart of pseudo_label."""
    input:
        samples=f"{DATA}/samples/attempt-{{attempt}}/{{domain}}/shard_{{shard}}",
    output:
        directory(f"{CARRIED}/attempt-{{attempt}}/{{domain}}/shard_{{shard}}"),
    wildcard_constraints:
        attempt="|".join(CARRIED_ATTEMPTS) or r"(?!)",
        shard=r"\d+",
    params:
        code=code("carry-labels"),
    log:
        "logs/downstream/carried_labels/attempt-{attempt}/{domain}_{shard}.log",
    benchmark:
        "benchmarks/out/downstream/carried_labels/attempt-{attempt}/{domain}_{shard}.tsv"
    conda:
        ENV
    resources:
        **job_resources("simulate_pool"),
    shell:
        "omnilidar carry-labels --samples {input.samples} --out {output} > {log} 2>&1"


rule pseudo_label_round_trip:
    """The labeler's labels of the round-tripped pool (the labels link), with their accuracy."""
    input:
        labeler=LABELER,
        pool=round_trip_pool_dir("{domain}", "{pct}", "{scans}"),
    output:
        directory(round_trip_labels_dir("{domain}", "{pct}", "{scans}")),
    wildcard_constraints:
        domain="|".join(DOMAIN_NAMES),
        pct=r"\d+",
        scans=r"[1-9]\d*",
    params:
        settings=settings("downstream", "labeler"),
        code=code("pseudo-label"),
    log:
        "logs/downstream/pseudo_labels/round_trip_{domain}_{pct}pct_{scans}.log",
    conda:
        ENV
    threads: 1
    resources:
        **job_resources("pseudo_label"),
    shell:
        "omnilidar pseudo-label --labeler {input.labeler} --pool {input.pool}/pool.json "
        "--settings {params.settings:q} --threads {threads} --out {output} > {log} 2>&1"


if WEATHER_STUDY["domain"]:

    rule gda_decomposition_weather:
        """The decomposition for a weather domain, scored on its corrupted val sets: do the generator's
        weather scans carry to the downstream model, against the domain builder's simulation of them?"""
        input:
            evaluations=weather_evaluations(),
            pool_labels=pool_labels_dir(DECOMPOSITION["percent"], DECOMPOSITION_SCANS),
            labeler=LABELER_VAL,
        output:
            json=f"results/gda_decomposition_{WEATHER_STUDY['domain']}.json",
            table=f"results/tables/gda_decomposition_{WEATHER_STUDY['domain']}.html",
            figure=f"results/figures/gda_decomposition_{WEATHER_STUDY['domain']}.png",
        params:
            settings=settings("downstream", drop=("det",)),
            seed=config["seed"],
            data_source=data_source("semantickitti"),
            code=result_code("gda-decomposition"),
        log:
            "logs/downstream/gda_decomposition_weather.log",
        benchmark:
            "benchmarks/out/downstream/gda_decomposition_weather.tsv"
        conda:
            ENV
        resources:
            **job_resources("gda_result"),
        shell:
            with_table(
                "omnilidar gda-decomposition --evaluations {input.evaluations} --evalset "
                f"{WEATHER_STUDY['corruption']} --domain {WEATHER_STUDY['domain']} "
                "--pool-labels {input.pool_labels} --labeler-evaluation {input.labeler} --settings {params.settings:q} "
                "--seed {params.seed} --data-source {params.data_source:q} --out {output.json} "
                "--figure {output.figure} > {log} 2>&1"
            )


rule segmentation:
    """Every segmentation experiment target."""
    input:
        expand("results/semkitti_{pct}pct.json", pct=EXPERIMENTS["semkitti"]["percents"]),
        "results/semkittic.json",
        expand("results/nusc_beam32_{pct}pct.json", pct=EXPERIMENTS["nusc_beam32"]["percents"]),
        "results/semanticstf.json",
        "results/gda_curve.json",
        "results/gda_decomposition.json",
