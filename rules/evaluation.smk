# Evaluation stage: metric extractors (official weights or self-trained on the real
# training split), the paper's generation tables, the sampler accuracy/time study and
# the generator evidence. Needs rules/generator.smk and rules/domains.smk included first;
# the study's downstream panel reads results/gda_curve.json (rules/downstream.smk).

EXTRACTORS = f"{DATA}/extractors"
SINGLE_DOMAIN = f"{DATA}/generator_single"
EVAL = config["evaluation"]
# The generator's domain labels (prompt pools), e.g. Vehicle, WetGround.
GEN_DOMAINS = list(config["generator"]["prompts"])
METRIC_KIND = {"FRD": "frd", "FRID": "frid", "FSVD": "fsvd", "FPVD": "fpvd", "FPD": "fpd"}


GQ_WEIGHTS = extractor_weights(EVAL["generation_quality"]["metrics"])
ABL_WEIGHTS = extractor_weights(EVAL["ablation"]["metrics"])
K360_WEIGHTS = extractor_weights(EVAL["kitti360"]["metrics"])
TRADEOFF_WEIGHTS = extractor_weights([EVAL["tradeoff"]["feature_metric"]])
# Settings a stage does not read stay out of its params, so changing them reruns nothing.
TABLES = ("generation_quality", "ablation", "kitti360", "tradeoff", "evidence")


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
        gpu=1,
        mem_mb=8000,
        runtime=6 * 60,
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
        gpu=1,
        mem_mb=32000,
        runtime=24 * 60,
    shell:
        "omnilidar train-generator --domains {input.domains} --prompts {input.prompts} "
        "--preset single_domain --settings {params.settings:q} --seed {params.seed} "
        "--work-dir {params.work_dir} --out {output} > {log} 2>&1"


rule generation_quality:
    """8 domains x FRD/FRID/FPVD/FSVD/JSD/MMD: OmniLiDAR against single-domain baselines."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
        full=f"{GENERATOR}/full/model.pt",
        baselines=expand(f"{SINGLE_DOMAIN}/{{domain}}/model.pt", domain=GEN_DOMAINS),
        weights=list(GQ_WEIGHTS.values()),
    output:
        json="results/generation_quality.json",
        markdown=report("results/generation_quality.md", caption="../workflow/report/generation_quality.rst", category="Generation"),
        figure=report("results/figures/generation_quality.png", caption="../workflow/report/generation_quality.rst", category="Generation"),
    params:
        settings=eval_settings("generation_quality"),
        seed=config["seed"],
        baselines=" ".join(f"--baseline {d}={SINGLE_DOMAIN}/{d}/model.pt" for d in GEN_DOMAINS),
        weights=weights_args(GQ_WEIGHTS),
        data_source=data_source(),
        code=code("generation-quality"),
    log:
        "logs/evaluation/generation_quality.log",
    benchmark:
        "benchmarks/out/evaluation/generation_quality.tsv"
    conda:
        ENV
    resources:
        gpu=1,
        mem_mb=16000,
        runtime=12 * 60,
    shell:
        "omnilidar generation-quality --domains {input.domains} --prompts {input.prompts} --full {input.full} "
        "{params.baselines} {params.weights} --settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
        "--out {output.json} --markdown {output.markdown} --figure {output.figure} > {log} 2>&1"


rule ablation_table:
    """The six configurations of the paper's ablation, averaged over the domains."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
        checkpoints=expand(f"{GENERATOR}/{{preset}}/model.pt", preset=EVAL["ablation"]["presets"]),
        weights=list(ABL_WEIGHTS.values()),
    output:
        json="results/ablation.json",
        markdown=report("results/ablation.md", caption="../workflow/report/ablation.rst", category="Generation"),
        figure=report("results/figures/ablation.png", caption="../workflow/report/ablation.rst", category="Generation"),
    params:
        settings=eval_settings("ablation"),
        seed=config["seed"],
        checkpoints=" ".join(f"--checkpoint {p}={GENERATOR}/{p}/model.pt" for p in EVAL["ablation"]["presets"]),
        weights=weights_args(ABL_WEIGHTS),
        data_source=data_source(),
        code=code("ablation-table"),
    log:
        "logs/evaluation/ablation.log",
    benchmark:
        "benchmarks/out/evaluation/ablation.tsv"
    conda:
        ENV
    resources:
        gpu=1,
        mem_mb=16000,
        runtime=12 * 60,
    shell:
        "omnilidar ablation-table --domains {input.domains} --prompts {input.prompts} {params.checkpoints} "
        "{params.weights} --settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
        "--out {output.json} --markdown {output.markdown} --figure {output.figure} > {log} 2>&1"


rule kitti360_generation:
    """KITTI-360 comparison: Vehicle samples against KITTI-360 scans (FRD, FPD, JSD, MMD)."""
    input:
        index=f"{DATA}/index/kitti360.json",
        prompts=rules.encode_prompts.output,
        full=f"{GENERATOR}/full/model.pt",
        baseline=f"{SINGLE_DOMAIN}/{EVAL['kitti360']['domain']}/model.pt",
        weights=list(K360_WEIGHTS.values()),
    output:
        json="results/kitti360_generation.json",
        markdown=report("results/kitti360_generation.md", caption="../workflow/report/kitti360_generation.rst", category="Generation"),
        figure=report("results/figures/kitti360_generation.png", caption="../workflow/report/kitti360_generation.rst", category="Generation"),
    params:
        settings=eval_settings("kitti360"),
        seed=config["seed"],
        weights=weights_args(K360_WEIGHTS),
        data_source=data_source("kitti360"),
        code=code("kitti360-generation"),
    log:
        "logs/evaluation/kitti360_generation.log",
    benchmark:
        "benchmarks/out/evaluation/kitti360_generation.tsv"
    conda:
        ENV
    resources:
        gpu=1,
        mem_mb=16000,
        runtime=6 * 60,
    shell:
        "omnilidar kitti360-generation --index {input.index} --prompts {input.prompts} --full {input.full} "
        "--baseline {input.baseline} {params.weights} --settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
        "--out {output.json} --markdown {output.markdown} --figure {output.figure} > {log} 2>&1"


rule sampler_tradeoff:
    """Samplers x steps: per-domain JSD, MMD and the cheapest feature metric against seconds
    per scan, measured in one run; Pareto front; the effects' curves; downstream mIoU
    against the compute of generated scans (results/gda_curve.json)."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
        checkpoint=f"{GENERATOR}/full/model.pt",
        effects="results/effects_tradeoff.json",
        curve="results/gda_curve.json",
        weights=list(TRADEOFF_WEIGHTS.values()),
    output:
        json="results/tradeoff.json",
        figure=report("results/figures/tradeoff.png", caption="../workflow/report/tradeoff.rst", category="Accuracy vs time"),
    params:
        settings=eval_settings("tradeoff"),
        seed=config["seed"],
        weights=weights_args(TRADEOFF_WEIGHTS),
        data_source=data_source(),
        code=code("sampler-tradeoff"),
    log:
        "logs/evaluation/tradeoff.log",
    benchmark:
        "benchmarks/out/evaluation/tradeoff.tsv"
    conda:
        ENV
    resources:
        gpu=1,
        mem_mb=16000,
        runtime=12 * 60,
    shell:
        "omnilidar sampler-tradeoff --domains {input.domains} --prompts {input.prompts} "
        "--checkpoint {input.checkpoint} {params.weights} --effects {input.effects} "
        "--gda-curve {input.curve} --settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
        "--out {output.json} --figure {output.figure} > {log} 2>&1"


rule generator_evidence:
    """The trained generator against an untrained one (same architecture and seed), and
    domain statistics of generated vs real scans per domain."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
        checkpoint=f"{GENERATOR}/full/model.pt",
    output:
        json="results/generator_evidence.json",
        markdown=report("results/generator_evidence.md", caption="../workflow/report/generator_evidence.rst", category="Generation"),
        figure=report("results/figures/generator_evidence.png", caption="../workflow/report/generator_evidence.rst", category="Generation"),
    params:
        settings=settings("evaluation", drop=("extractors", *[t for t in TABLES if t != "evidence"])),
        seed=config["seed"],
        data_source=data_source(),
        code=code("generator-evidence"),
    log:
        "logs/evaluation/generator_evidence.log",
    benchmark:
        "benchmarks/out/evaluation/generator_evidence.tsv"
    conda:
        ENV
    resources:
        mem_mb=8000,
        runtime=60,
    shell:
        "omnilidar generator-evidence --domains {input.domains} --prompts {input.prompts} "
        "--checkpoint {input.checkpoint} --settings {params.settings:q} --seed {params.seed} --data-source {params.data_source:q} "
        "--out {output.json} --markdown {output.markdown} --figure {output.figure} > {log} 2>&1"


rule evaluation:
    """Every generation-quality target."""
    input:
        "results/generation_quality.json",
        "results/ablation.json",
        "results/kitti360_generation.json",
        "results/tradeoff.json",
        "results/generator_evidence.json",
