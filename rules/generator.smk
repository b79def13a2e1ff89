# Generator stage: encode the domain prompts once, train the diffusion model on all
# built domains, and sample every domain as parallel shard jobs.

GENERATOR = f"{DATA}/generator"
# generator_launcher(): torchrun with one process per GPU when resources.generator_gpus > 1.
TRAIN_GENERATOR_SHELL = (
    generator_launcher() + " train-generator --domains {{input.domains}} --prompts {{input.prompts}} "
    "--preset {preset} --settings {{params.settings:q}} --seed {{params.seed}} "
    "--work-dir {{params.work_dir}} --threads {{threads}} --out {{output}}{until} > {{log}} 2>&1"
)
SAMPLE_SHELL = (
    "omnilidar sample --checkpoint {input.checkpoint} --prompts {input.prompts} "
    "--domain {wildcards.domain} --shard {wildcards.shard} {params.sources}--settings {params.settings:q} "
    "--seed {params.seed} --threads {threads} --out {output} > {log} 2>&1"
)


rule encode_prompts:
    """Token embeddings of every prompt, cached so training never loads the text encoder."""
    output:
        f"{GENERATOR}/prompts.pt",
    params:
        # Only the encoder and the prompt pools matter here.
        settings=json.dumps({k: config["generator"][k] for k in ("text", "prompts")}, sort_keys=True),
        code=code("encode-prompts"),
    log:
        "logs/generator/encode_prompts.log",
    benchmark:
        "benchmarks/out/generator/encode_prompts.tsv"
    conda:
        ENV
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("encode_prompts"),
    shell:
        "omnilidar encode-prompts --settings {params.settings:q} --out {output} > {log} 2>&1"


rule train_generator_segment:
    """One segment of a generator training longer than its partition allows (resources.smk cuts
    it where the partition's time limit falls): trains up to iteration `until` from the previous
    segment's state in work/generator/<preset> and leaves its own there; the chain ends in
    train_generator, with the weights of one uninterrupted run."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
        previous=previous_generator_segment,
    output:
        generator_segment("{preset}", "{until}"),
    wildcard_constraints:
        preset="single_domain|batch_homogeneous|cdts|cdts_cdfm|cdts_dafs|full",
        until=r"\d+",
    params:
        settings=settings("generator", drop=("sampling", "distillation")),
        seed=config["seed"],
        work_dir=lambda w: f"work/generator/{w.preset}",
        code=code("train-generator"),
    log:
        "logs/generator/train_{preset}_until_{until}.log",
    benchmark:
        "benchmarks/out/generator/train_{preset}_until_{until}.tsv"
    conda:
        ENV
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("train_generator_segment"),
    shell:
        TRAIN_GENERATOR_SHELL.format(preset="{wildcards.preset}", until=" --until {wildcards.until}")


rule train_generator:
    """Train the generator (a preset of the paper's ablation; `full` is OmniLiDAR).
    Resumable state lives in work/generator/<preset>, which is not a declared output; where the
    training outlasts its partition's time limit, this is the last job of a segment chain."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
        previous=previous_generator_segment,
    output:
        f"{GENERATOR}/{{preset}}/model.pt",
    wildcard_constraints:
        preset="single_domain|batch_homogeneous|cdts|cdts_cdfm|cdts_dafs|full",
    params:
        settings=settings("generator", drop=("sampling", "distillation")),
        seed=config["seed"],
        work_dir=lambda w: f"work/generator/{w.preset}",
        code=code("train-generator"),
    log:
        "logs/generator/train_{preset}.log",
    benchmark:
        "benchmarks/out/generator/train_{preset}.tsv"
    conda:
        ENV
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("train_generator"),
    shell:
        TRAIN_GENERATOR_SHELL.format(preset="{wildcards.preset}", until="")


rule distill_generator:
    """Progressive distillation of the trained generator into a student that samples in a few DDIM
    steps (generator.distillation); resumable state in work/generator/<preset>_student.
    generator.sampling.student: true makes sample_domain use it."""
    input:
        teacher=f"{GENERATOR}/{{preset}}/model.pt",
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
    output:
        f"{GENERATOR}/{{preset}}/student.pt",
    wildcard_constraints:
        preset="single_domain|batch_homogeneous|cdts|cdts_cdfm|cdts_dafs|full",
    params:
        settings=settings("generator", drop=("sampling",)),
        seed=config["seed"],
        work_dir=lambda w: f"work/generator/{w.preset}_student",
        code=code("distill-generator"),
    log:
        "logs/generator/distill_{preset}.log",
    benchmark:
        "benchmarks/out/generator/distill_{preset}.tsv"
    conda:
        ENV
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("distill_generator"),
    shell:
        "omnilidar distill-generator --teacher {input.teacher} --domains {input.domains} --prompts {input.prompts} "
        "--preset {wildcards.preset} --settings {params.settings:q} --seed {params.seed} "
        "--work-dir {params.work_dir} --threads {threads} --out {output} > {log} 2>&1"


rule sample_domain:
    """One shard of generated scans of one domain (range images + SemanticKITTI points), from the
    generator or, with generator.sampling.student, from its distilled student."""
    input:
        checkpoint=sampling_checkpoint("full"),
        prompts=rules.encode_prompts.output,
        sources=edit_sources(config["generator"]["sampling"]),
    output:
        directory(f"{DATA}/samples/{{domain}}/shard_{{shard}}"),
    wildcard_constraints:
        domain=r"[^/]+",
        shard=r"\d+",
    params:
        settings=settings("generator", drop=("distillation",)),
        sources=sources_arg,
        seed=config["seed"],
        code=code("sample"),
    log:
        "logs/samples/{domain}_{shard}.log",
    benchmark:
        "benchmarks/out/samples/{domain}_{shard}.tsv"
    conda:
        ENV
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("sample_domain"),
    shell:
        SAMPLE_SHELL


rule train_generator_attempt:
    """The generator of a GDA decomposition attempt that changes it (attempts.<name>.generator laid
    over the generator section, e.g. a longer run): OmniLiDAR's full preset, its own work dir."""
    input:
        domains=f"{DATA}/domains/index.json",
        prompts=rules.encode_prompts.output,
    output:
        f"{GENERATOR}/attempt-{{attempt}}/model.pt",
    wildcard_constraints:
        attempt=generator_attempt_pattern(),
    params:
        settings=lambda w: attempt_generator_settings(w.attempt, drop=("sampling", "distillation")),
        seed=config["seed"],
        work_dir=lambda w: f"work/generator/attempt-{w.attempt}",
        code=code("train-generator"),
    log:
        "logs/generator/train_attempt-{attempt}.log",
    benchmark:
        "benchmarks/out/generator/train_attempt-{attempt}.tsv"
    conda:
        ENV
    resources:
        **job_resources("train_generator"),
    shell:
        TRAIN_GENERATOR_SHELL.format(preset="full", until="")


rule sample_attempt:
    """One shard of a domain's scans for a decomposition attempt that changes the generator: from its
    own generator, or, where it changes only sampling (e.g. the distilled student), the main one."""
    input:
        checkpoint=lambda w: attempt_checkpoint(w.attempt),
        prompts=rules.encode_prompts.output,
        sources=lambda w: edit_sources(json.loads(attempt_generator_settings(w.attempt))["sampling"]),
    output:
        directory(f"{DATA}/samples/attempt-{{attempt}}/{{domain}}/shard_{{shard}}"),
    wildcard_constraints:
        attempt=generator_attempt_pattern(trained=False),
        domain=r"[^/]+",
        shard=r"\d+",
    params:
        settings=lambda w: attempt_generator_settings(w.attempt),
        sources=sources_arg,
        seed=config["seed"],
        code=code("sample"),
    log:
        "logs/samples/attempt-{attempt}/{domain}_{shard}.log",
    benchmark:
        "benchmarks/out/samples/attempt-{attempt}/{domain}_{shard}.tsv"
    conda:
        ENV
    resources:
        **job_resources("sample_domain"),
    shell:
        SAMPLE_SHELL


rule samples:
    """Every domain's samples."""
    input:
        [shard for name in DOMAIN_NAMES for shard in sample_shards(domain_label(name))],
