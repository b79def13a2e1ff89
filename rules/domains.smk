# Domain stage: build every configured domain as shards of range images and point
# files, the SemanticKITTI-C-style corrupted sets, and the effect reports.

DOMAINS = f"{DATA}/domains"
# Each domain's held-out reference set (its heldout_split), the sampler study's real scans.
HELDOUT_DOMAINS = f"{DATA}/domains_heldout"
# CORRUPTED (the corrupted sets' folder) is in rules/common.smk, whose helpers name it.


# Every shard directory (one build_domain job each), every corrupted set, and the scans of
# the two reports; plain values, not functions (helpers live in common.smk).
DOMAIN_SHARD_DIRS = [
    f"{DOMAINS}/{name}/shard_{k}" for name in DOMAIN_NAMES for k in range(config["domains"][name]["num_shards"])
]
CORRUPTED_SET_DIRS = expand(
    f"{CORRUPTED}/{{corruption}}/{{severity}}",
    corruption=config["domains"]["corrupted"]["corruptions"],
    severity=config["domains"]["corrupted"]["severities"],
)
FIDELITY_SCANS = config["domains"]["fidelity"]["scans"]
TRADEOFF_SCANS = config["domains"]["tradeoff"]["scans"] or FIDELITY_SCANS[:1]
# Without listed scans the reports run on the first scans of the SemanticKITTI index (the
# synthetic world's full HDL-64E sweeps in the embedded default), a real input of their jobs.
FIDELITY_INDEX = [] if FIDELITY_SCANS else f"{DATA}/index/semantickitti.json"
TRADEOFF_INDEX = [] if TRADEOFF_SCANS else f"{DATA}/index/semantickitti.json"


rule build_domain:
    """One shard of a domain: every num_shards-th scan of its source split, with the
    domain's scene spec applied (per-scan seeds do not depend on the sharding)."""
    input:
        lambda w: f"{DATA}/index/{config['domains'][w.domain]['dataset']}.json",
    output:
        directory(f"{DOMAINS}/{{domain}}/shard_{{shard}}"),
    wildcard_constraints:
        domain="|".join(DOMAIN_NAMES),
        shard=r"\d+",
    params:
        num_shards=lambda w: config["domains"][w.domain]["num_shards"],
        settings=lambda w: domain_settings(w.domain),
        seed=config["seed"],
        code=lambda w: domain_code(w.domain),
    log:
        f"logs/domains/{{domain}}_{{shard}}.log",
    benchmark:
        f"benchmarks/out/domains/{{domain}}_{{shard}}.tsv"
    conda:
        ENV
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("build_domain"),
    shell:
        "omnilidar build-domain {wildcards.domain} --index {input} --shard {wildcards.shard} "
        "--num-shards {params.num_shards} --settings {params.settings:q} --seed {params.seed} "
        "--out {output} > {log} 2>&1"


rule domains_index:
    """Which shard directories hold each domain, for the generator."""
    input:
        DOMAIN_SHARD_DIRS,
    output:
        f"{DOMAINS}/index.json",
    params:
        settings=domains_settings(),
        code=code("domains-index"),
    log:
        "logs/domains/index.log",
    benchmark:
        "benchmarks/out/domains/index.tsv"
    conda:
        ENV
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("domains_index"),
    shell:
        "omnilidar domains-index --settings {params.settings:q} --out {output} {input} > {log} 2>&1"


rule build_heldout_domain:
    """A domain's held-out reference set: its scene spec on its heldout_split (scans the generator
    never trains on), the real scans the sampler study scores every setting against."""
    input:
        lambda w: f"{DATA}/index/{config['domains'][w.domain]['dataset']}.json",
    output:
        directory(f"{HELDOUT_DOMAINS}/{{domain}}/shard_0"),
    wildcard_constraints:
        domain="|".join(DOMAIN_NAMES),
    params:
        settings=lambda w: heldout_domain_settings(w.domain),
        seed=config["seed"],
        code=lambda w: domain_code(w.domain),
    log:
        f"logs/domains_heldout/{{domain}}.log",
    benchmark:
        f"benchmarks/out/domains_heldout/{{domain}}.tsv"
    conda:
        ENV
    resources:
        **job_resources("build_heldout_domain"),
    shell:
        "omnilidar build-domain {wildcards.domain} --index {input} --shard 0 --num-shards 1 "
        "--settings {params.settings:q} --seed {params.seed} --out {output} > {log} 2>&1"


rule heldout_domains_index:
    """Which shard directory holds each domain's held-out set."""
    input:
        [f"{HELDOUT_DOMAINS}/{name}/shard_0" for name in DOMAIN_NAMES],
    output:
        f"{HELDOUT_DOMAINS}/index.json",
    params:
        settings=lambda w: heldout_domains_settings(),
        code=code("domains-index"),
    log:
        "logs/domains_heldout/index.log",
    benchmark:
        "benchmarks/out/domains_heldout/index.tsv"
    conda:
        ENV
    resources:
        **job_resources("heldout_domains_index"),
    shell:
        "omnilidar domains-index --settings {params.settings:q} --out {output} {input} > {log} 2>&1"


rule build_corrupted:
    """One SemanticKITTI-C-style set: a corruption at a fixed severity on the val split."""
    input:
        f"{DATA}/index/{config['domains']['corrupted']['dataset']}.json",
    output:
        directory(f"{CORRUPTED}/{{corruption}}/{{severity}}"),
    wildcard_constraints:
        corruption=r"fog|wet_ground|snow|beam_missing",
        severity=r"light|moderate|heavy",
    params:
        settings=domains_settings(),
        seed=config["seed"],
        code=code("build-corrupted"),
    log:
        f"logs/corrupted/{{corruption}}_{{severity}}.log",
    benchmark:
        f"benchmarks/out/corrupted/{{corruption}}_{{severity}}.tsv"
    conda:
        ENV
    resources:
        **job_resources("build_corrupted"),
    shell:
        "omnilidar build-corrupted {wildcards.corruption} {wildcards.severity} --index {input} "
        "--settings {params.settings:q} --seed {params.seed} --out {output} > {log} 2>&1"


rule domain_fidelity:
    """Per effect and severity on KITTI-format scans: points changed, lost and added, weather-return
    distributions, intensity shift and time per scan, beside the anchors' numbers."""
    input:
        scans=FIDELITY_SCANS,
        index=FIDELITY_INDEX,
    output:
        json="results/domain_fidelity.json",
        table="results/tables/domain_fidelity.html",
        figure="results/figures/domain_fidelity.png",
    params:
        settings=domains_settings(),
        seed=config["seed"],
        code=result_code("domain-fidelity"),
        index=lambda w, input: f"--index {input.index}" if input.index else "",
    log:
        "logs/domain_fidelity.log",
    benchmark:
        "benchmarks/out/domain_fidelity.tsv"
    conda:
        ENV
    resources:
        **job_resources("domain_fidelity"),
    shell:
        with_table(
            "omnilidar domain-fidelity --settings {params.settings:q} --seed {params.seed} "
            "--out {output.json} --figure {output.figure} {params.index} {input.scans} > {log} 2>&1"
        )


rule effects_tradeoff:
    """Error against time per scan for every numerical knob of every effect, defaults marked."""
    input:
        scans=TRADEOFF_SCANS,
        index=TRADEOFF_INDEX,
    output:
        json="results/effects_tradeoff.json",
        table="results/tables/effects_tradeoff.html",
        figure="results/figures/effects_tradeoff.png",
    params:
        settings=domains_settings(),
        seed=config["seed"],
        code=result_code("effects-tradeoff"),
        index=lambda w, input: f"--index {input.index}" if input.index else "",
    log:
        "logs/effects_tradeoff.log",
    benchmark:
        "benchmarks/out/effects_tradeoff.tsv"
    conda:
        ENV
    resources:
        **job_resources("effects_tradeoff"),
    shell:
        with_table(
            "omnilidar effects-tradeoff --settings {params.settings:q} --seed {params.seed} "
            "--out {output.json} --figure {output.figure} {params.index} {input.scans} > {log} 2>&1"
        )


rule domains:
    """Every configured domain (and its index) and every corrupted set."""
    input:
        f"{DOMAINS}/index.json",
        DOMAIN_SHARD_DIRS,
        CORRUPTED_SET_DIRS,
