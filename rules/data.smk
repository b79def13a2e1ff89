# Data stage: generate the synthetic datasets (when no real root is configured),
# index every dataset, and summarise scene statistics.

SYNTH = f"{DATA}/synthetic"

# One job per shard (sequence, platform or split), never one job per scan.
SYNTHESIZE = (
    "omnilidar synthesize {params.dataset} --shard {params.shard} --settings {params.settings:q} "
    "--seed {params.seed} --out {output} > {log} 2>&1"
)


rule synthesize:
    """One shard of one synthetic dataset, in that dataset's own layout."""
    output:
        directory(f"{SYNTH}/{{dataset}}/{{shard_dir}}"),
    wildcard_constraints:
        dataset="|".join(SYNTHETIC_SHARD_LAYOUT),
        shard_dir=synthetic_shard_dir_regex(),
    params:
        dataset=lambda w: w.dataset,
        shard=lambda w: synthetic_shard(w.dataset, w.shard_dir),
        settings=lambda w: synthetic_shard_settings(w.dataset, w.shard_dir),
        seed=config["seed"],
        code=code("synthesize"),
    log:
        f"logs/synthesize/{{dataset}}/{{shard_dir}}.log",
    benchmark:
        f"benchmarks/out/synthesize/{{dataset}}/{{shard_dir}}.tsv"
    conda:
        ENV
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("synthesize"),
    shell:
        SYNTHESIZE


rule index_dataset:
    """List every scan (and label) of a dataset per split, checking file sizes, so
    later stages read one small JSON instead of walking the dataset."""
    input:
        lambda w: synthetic_shard_dirs(w.dataset) if is_synthetic(w.dataset) else [],
    output:
        f"{DATA}/index/{{dataset}}.json",
    wildcard_constraints:
        dataset=r"semantickitti|kitti360|pi3det|nuscenes",
    params:
        root=lambda w: dataset_root(w.dataset),
        source=lambda w: "synthetic" if is_synthetic(w.dataset) else "real",
        settings=lambda w: settings("datasets", w.dataset),
        # A real root has no declared inputs: its listing (names, sizes, modification times)
        # is a param, so adding, removing or replacing scans or labels reindexes it.
        listing=lambda w: "" if is_synthetic(w.dataset) else root_listing(dataset_root(w.dataset)),
        code=code("index-dataset"),
    log:
        f"logs/index/{{dataset}}.log",
    benchmark:
        f"benchmarks/out/index/{{dataset}}.tsv"
    conda:
        ENV
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("index_dataset"),
    shell:
        "omnilidar index-dataset {wildcards.dataset} --root {params.root:q} --source {params.source} "
        "--out {output} > {log} 2>&1"


rule data_summary:
    """Scene statistics of every dataset beside real KITTI (class frequencies,
    points per scan, range and elevation profiles), with a figure."""
    input:
        expand(f"{DATA}/index/{{dataset}}.json", dataset=["semantickitti", "kitti360", "pi3det", "nuscenes"]),
    output:
        json="results/data_summary.json",
        table="results/tables/data_summary.html",
        figure="results/figures/data_summary.png",
    params:
        settings=settings("data_summary"),
        seed=config["seed"],
        code=result_code("summarize-data"),
    log:
        "logs/data_summary.log",
    benchmark:
        "benchmarks/out/data_summary.tsv"
    conda:
        ENV
    resources:
        **job_resources("data_summary"),
    shell:
        with_table(
            "omnilidar summarize-data {input} --settings {params.settings:q} --seed {params.seed} "
            "--out {output.json} --figure {output.figure} > {log} 2>&1"
        )
