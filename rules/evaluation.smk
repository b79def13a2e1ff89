# Evaluation stage: metric extractors (official weights or self-trained on the real
# training split), the paper's generation tables, the sampler accuracy/time study and
# the generator evidence. Needs rules/generator.smk and rules/domains.smk included first;
# the study's downstream panel reads results/gda_curve.json (rules/downstream.smk).

# EXTRACTORS, EVAL, METRIC_KIND and TABLES are in rules/common.smk, whose helpers read them;
# SINGLE_DOMAIN and the generated sets' helpers in rules/evaluation_sets.smk.
# The generator's domain labels (prompt pools), e.g. Vehicle, WetGround.
GEN_DOMAINS = list(config["generator"]["prompts"])


GQ_WEIGHTS = extractor_weights(EVAL["generation_quality"]["metrics"])
ABL_WEIGHTS = extractor_weights(EVAL["ablation"]["metrics"])
K360_WEIGHTS = extractor_weights(EVAL["kitti360"]["metrics"])
TRADEOFF_WEIGHTS = extractor_weights(EVAL["tradeoff"]["feature_metrics"])


# Generated sets of the tables: sample shard jobs (rules/evaluation_sets.smk).
GQ_SETS = table_sets({"full": "full", "baseline": lambda d: f"baseline-{d}"}, GEN_DOMAINS)
ABL_SETS = table_sets({p: p for p in EVAL["ablation"]["presets"]}, GEN_DOMAINS)
K360_DOMAIN = EVAL["kitti360"]["domain"]
K360_SETS = generated_sets({
    "full": ("full", K360_DOMAIN, EVAL["sampler"], EVAL["steps"], EVAL["scans_per_set"]),
    "baseline": (f"baseline-{K360_DOMAIN}", K360_DOMAIN, EVAL["sampler"], EVAL["steps"], EVAL["scans_per_set"]),
})
# Every setting of the sampler study is sampled and timed alike (the generator's own included).
TRADEOFF_SETS = generated_sets({f"{s}-{n}/{d}": ("full", d, s, n, EVAL["tradeoff"]["scans"])
                                for s, steps in EVAL["tradeoff"]["samplers"].items() for n in steps
                                for d in (EVAL["tradeoff"]["domains"] or GEN_DOMAINS)}, reuse=False)
# The distilled student, sampled (DDIM in its own steps) beside the teacher's solvers.
TRADEOFF_STUDENT = [f"{GENERATOR}/full/student.pt"] if EVAL["tradeoff"]["student"] else []
if TRADEOFF_STUDENT:
    TRADEOFF_SETS |= generated_sets({f"student-{STUDENT_STEPS}/{d}": ("student", d, "ddim", STUDENT_STEPS,
                                                                       EVAL["tradeoff"]["scans"])
                                     for d in (EVAL["tradeoff"]["domains"] or GEN_DOMAINS)})


rule sample_eval:
    """One shard of a generated set of the generation tables (a preset or baseline, sampler, steps)."""
    input:
        checkpoint=lambda w: eval_checkpoint(w.model),
        prompts=rules.encode_prompts.output,
    output:
        directory(f"{DATA}/eval_samples/{{model}}/{{sampler}}_{{steps}}/{{domain}}/shard_{{shard}}"),
    wildcard_constraints:
        model=r"[a-z_]+|baseline-\w+",
        sampler=r"[a-z]+(_[a-z0-9]+)*",
        steps=r"\d+",
        shard=r"\d+",
    params:
        settings=lambda w: eval_sampling_settings(w.sampler, w.steps),
        seed=config["seed"],
        code=code("sample"),
    log:
        "logs/eval_samples/{model}/{sampler}_{steps}/{domain}_{shard}.log",
    benchmark:
        "benchmarks/out/eval_samples/{model}/{sampler}_{steps}/{domain}_{shard}.tsv"
    conda:
        ENV
    resources:
        **job_resources("sample_eval"),
    shell:
        "omnilidar sample --checkpoint {input.checkpoint} --prompts {input.prompts} "
        "--domain {wildcards.domain} --shard {wildcards.shard} --settings {params.settings:q} "
        "--seed {params.seed} --threads {threads} --out {output} > {log} 2>&1"


rule train_extractor:
    """A metric extractor self-trained on the labelled real training split (only when no
    official weights are configured for it); numbers it produces are tagged self-trained."""
    input:
        f"{DATA}/index/semantickitti.json",
    output:
        f"{EXTRACTORS}/{{extractor}}.pt",
    wildcard_constraints:
        extractor=r"frd|frid|fsvd|fpvd|fpd",
    params:
        settings=json.dumps({"extractors": config["evaluation"]["extractors"]}, sort_keys=True),
        range_image=json.dumps(config["generator"]["range_image"], sort_keys=True),
        seed=config["seed"],
        code=code("train-extractor"),
    log:
        "logs/evaluation/train_extractor_{extractor}.log",
    benchmark:
        "benchmarks/out/evaluation/train_extractor_{extractor}.tsv"
    conda:
        ENV
    resources:
        **job_resources("train_extractor"),
    shell:
        "omnilidar train-extractor --extractor {wildcards.extractor} --index {input} "
        "--settings {params.settings:q} --range-image {params.range_image:q} "
        "--seed {params.seed} --out {output} > {log} 2>&1"


rule train_single_domain:
    """The R2DM-equivalent baseline: the single_domain preset trained on one domain only."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
    output:
        f"{SINGLE_DOMAIN}/{{domain}}/model.pt",
    wildcard_constraints:
        domain="|".join(GEN_DOMAINS),
    params:
        settings=lambda w: single_domain_settings(w.domain),
        seed=config["seed"],
        work_dir=lambda w: f"work/generator_single/{w.domain}",
        code=code("train-generator"),
    log:
        "logs/generator/train_single_{domain}.log",
    benchmark:
        "benchmarks/out/generator/train_single_{domain}.tsv"
    conda:
        ENV
    resources:
        **job_resources("train_single_domain"),
    shell:
        generator_launcher() + " train-generator --domains {input.domains} --prompts {input.prompts} "
        "--preset single_domain --settings {params.settings:q} --seed {params.seed} "
        "--work-dir {params.work_dir} --threads {threads} --out {output} > {log} 2>&1"


rule generation_quality:
    """8 domains x FRD/FRID/FPVD/FSVD/JSD/MMD: OmniLiDAR against single-domain baselines."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
        full=f"{GENERATOR}/full/model.pt",
        baselines=expand(f"{SINGLE_DOMAIN}/{{domain}}/model.pt", domain=GEN_DOMAINS),
        weights=list(GQ_WEIGHTS.values()),
        samples=[d for dirs in GQ_SETS.values() for d in dirs],
    output:
        json="results/generation_quality.json",
        table="results/tables/generation_quality.html",
        markdown="results/generation_quality.md",
        figure="results/figures/generation_quality.png",
    params:
        settings=eval_settings("generation_quality"),
        seed=config["seed"],
        baselines=" ".join(f"--baseline {d}={SINGLE_DOMAIN}/{d}/model.pt" for d in GEN_DOMAINS),
        weights=weights_args(GQ_WEIGHTS),
        samples=sets_args(GQ_SETS),
        data_source=data_source(),
        code=result_code("generation-quality"),
    log:
        "logs/evaluation/generation_quality.log",
    benchmark:
        "benchmarks/out/evaluation/generation_quality.tsv"
    conda:
        ENV
    resources:
        **job_resources("generation_quality"),
    shell:
        with_table(
            "omnilidar generation-quality --domains {input.domains} --prompts {input.prompts} --full {input.full} "
            "{params.baselines} {params.weights} {params.samples} --settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
            "--out {output.json} --markdown {output.markdown} --figure {output.figure} > {log} 2>&1"
        )


rule ablation_table:
    """The six configurations of the paper's ablation, averaged over the domains."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
        checkpoints=expand(f"{GENERATOR}/{{preset}}/model.pt", preset=EVAL["ablation"]["presets"]),
        weights=list(ABL_WEIGHTS.values()),
        samples=[d for dirs in ABL_SETS.values() for d in dirs],
    output:
        json="results/ablation.json",
        table="results/tables/ablation.html",
        markdown="results/ablation.md",
        figure="results/figures/ablation.png",
    params:
        settings=eval_settings("ablation"),
        seed=config["seed"],
        checkpoints=" ".join(f"--checkpoint {p}={GENERATOR}/{p}/model.pt" for p in EVAL["ablation"]["presets"]),
        weights=weights_args(ABL_WEIGHTS),
        samples=sets_args(ABL_SETS),
        data_source=data_source(),
        code=result_code("ablation-table"),
    log:
        "logs/evaluation/ablation.log",
    benchmark:
        "benchmarks/out/evaluation/ablation.tsv"
    conda:
        ENV
    resources:
        **job_resources("ablation_table"),
    shell:
        with_table(
            "omnilidar ablation-table --domains {input.domains} --prompts {input.prompts} {params.checkpoints} "
            "{params.weights} {params.samples} --settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
            "--out {output.json} --markdown {output.markdown} --figure {output.figure} > {log} 2>&1"
        )


rule kitti360_generation:
    """KITTI-360 comparison: Vehicle samples against KITTI-360 scans (FRD, FPD, JSD, MMD)."""
    input:
        index=f"{DATA}/index/kitti360.json",
        prompts=rules.encode_prompts.output,
        full=f"{GENERATOR}/full/model.pt",
        baseline=f"{SINGLE_DOMAIN}/{EVAL['kitti360']['domain']}/model.pt",
        weights=list(K360_WEIGHTS.values()),
        samples=[d for dirs in K360_SETS.values() for d in dirs],
    output:
        json="results/kitti360_generation.json",
        table="results/tables/kitti360_generation.html",
        markdown="results/kitti360_generation.md",
        figure="results/figures/kitti360_generation.png",
    params:
        settings=eval_settings("kitti360"),
        seed=config["seed"],
        weights=weights_args(K360_WEIGHTS),
        samples=sets_args(K360_SETS),
        data_source=data_source("kitti360"),
        code=result_code("kitti360-generation"),
    log:
        "logs/evaluation/kitti360_generation.log",
    benchmark:
        "benchmarks/out/evaluation/kitti360_generation.tsv"
    conda:
        ENV
    resources:
        **job_resources("kitti360_generation"),
    shell:
        with_table(
            "omnilidar kitti360-generation --index {input.index} --prompts {input.prompts} --full {input.full} "
            "--baseline {input.baseline} {params.weights} {params.samples} --settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
            "--out {output.json} --markdown {output.markdown} --figure {output.figure} > {log} 2>&1"
        )


rule sampler_tradeoff:
    """Samplers x steps: per-domain JSD, MMD and the cheapest feature metric against seconds
    per scan, measured in one run; Pareto front; the effects' curves; downstream mIoU
    against the compute of generated scans (results/gda_curve.json)."""
    input:
        domains=f"{DATA}/domains/index.json",
        # The real scans: each domain's held-out set, or (reference: training) its training scans.
        reference=f"{HELDOUT_DOMAINS if EVAL['tradeoff']['reference'] == 'heldout' else DOMAINS}/index.json",
        prompts=rules.encode_prompts.output,
        checkpoint=f"{GENERATOR}/full/model.pt",
        effects="results/effects_tradeoff.json",
        curve=["results/gda_curve.json"] if config["evaluation"]["tradeoff"]["downstream"] else [],
        weights=list(TRADEOFF_WEIGHTS.values()),
        samples=[d for dirs in TRADEOFF_SETS.values() for d in dirs],
        student=TRADEOFF_STUDENT,
    output:
        json="results/tradeoff.json",
        table="results/tables/tradeoff.html",
        figure="results/figures/tradeoff.png",
    params:
        settings=eval_settings("tradeoff"),
        seed=config["seed"],
        student=" ".join(f"--student {p}" for p in TRADEOFF_STUDENT) + tradeoff_default_sampler(),
        curve=lambda w, input: f"--gda-curve {input.curve}" if input.curve else "",
        weights=weights_args(TRADEOFF_WEIGHTS),
        samples=sets_args(TRADEOFF_SETS),
        data_source=data_source(),
        code=result_code("sampler-tradeoff"),
    log:
        "logs/evaluation/tradeoff.log",
    benchmark:
        "benchmarks/out/evaluation/tradeoff.tsv"
    conda:
        ENV
    resources:
        **job_resources("sampler_tradeoff"),
    shell:
        with_table(
            "omnilidar sampler-tradeoff --domains {input.domains} --reference {input.reference} --prompts {input.prompts} "
            "--checkpoint {input.checkpoint} {params.student} {params.weights} {params.samples} --effects {input.effects} "
            "{params.curve} --settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
            "--out {output.json} --figure {output.figure} > {log} 2>&1"
        )


rule generator_evidence:
    """The trained generator against an untrained one (same architecture and seed), and
    domain statistics of generated vs real scans per domain."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
        checkpoint=f"{GENERATOR}/full/model.pt",
    output:
        json="results/generator_evidence.json",
        table="results/tables/generator_evidence.html",
        markdown="results/generator_evidence.md",
        figure="results/figures/generator_evidence.png",
    params:
        settings=settings("evaluation", drop=("extractors", *[t for t in TABLES if t != "evidence"])),
        seed=config["seed"],
        data_source=data_source(),
        code=result_code("generator-evidence"),
    log:
        "logs/evaluation/generator_evidence.log",
    benchmark:
        "benchmarks/out/evaluation/generator_evidence.tsv"
    conda:
        ENV
    resources:
        **job_resources("generator_evidence"),
    shell:
        with_table(
            "omnilidar generator-evidence --domains {input.domains} --prompts {input.prompts} "
            "--checkpoint {input.checkpoint} --settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
            "--out {output.json} --markdown {output.markdown} --figure {output.figure} > {log} 2>&1"
        )


rule evaluation:
    """Every generation-quality target."""
    input:
        "results/generation_quality.json",
        "results/ablation.json",
        "results/kitti360_generation.json",
        "results/tradeoff.json",
        "results/generator_evidence.json",
