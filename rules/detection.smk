# Detection GDA stage on the Pi3DET platforms: the fixed box labeler per platform,
# pseudo-boxes of the platform's generated samples, Voxel R-CNN / PV-RCNN trained from
# scratch on real label subsets (supervised-only and GDA), evaluation and the targets
# results/pi3det_{platform}_{pct}pct.json.
#
# What each rule sees, so that only what changed reruns:
#   labeler, pseudo-boxes     data keys + labeler (+ the labeler detector's entry and yaml)
#   supervised-only runs      data keys + the run's detector entry and yaml, schedule, augmentation
#   GDA runs                  + sample shards, pseudo-boxes, mixing
#   evaluation                data keys + evaluation
# A platform's generated domain is the domains config key of the same name (drone, quadruped).

# DET, PSEUDO_BOXES, DET_SECTION, PI3DET_EXP and the detection helpers are in rules/common.smk.


BOX_LABELER = f"{DET}/{{platform}}/labeler.pt"
DETECTOR_REAL_RUN = f"{DET}/{{platform}}/{{detector}}_{{pct}}pct_real.pt"
DETECTOR_GDA_RUN = f"{DET}/{{platform}}/{{detector}}_{{pct}}pct_gda.pt"


rule train_box_labeler:
    """The fixed box labeler of one platform: the configured OpenPCDet checkpoint, or the
    labeler detector trained once on 100 % of the platform's real training frames."""
    input:
        index=lambda w: [] if labeler_checkpoint(w.platform) else f"{DATA}/index/pi3det.json",
        checkpoint=lambda w: labeler_checkpoint(w.platform) or [],
        model=lambda w: detector_yaml(DET_SECTION["labeler"]["detector"]),
        previous=previous_segment("train_box_labeler", BOX_LABELER),
    output:
        BOX_LABELER,
    wildcard_constraints:
        platform=PI3DET_PLATFORMS,
    params:
        settings=lambda w: det_settings("labeler", detector=DET_SECTION["labeler"]["detector"]),
        source=lambda w, input: f"--checkpoint {input.checkpoint}" if input.checkpoint else f"--index {input.index}",
        seed=config["seed"],
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        code=code("train-box-labeler"),
    log:
        f"logs/detection/labeler_{{platform}}.log",
    benchmark:
        f"benchmarks/out/detection/labeler_{{platform}}.tsv"
    conda:
        ENV
    threads: 1
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("train_box_labeler"),
    shell:
        "omnilidar train-box-labeler --platform {wildcards.platform} {params.source} --model-config {input.model} "
        "--settings {params.settings:q} --seed {params.seed} --work-dir {params.work_dir} --threads {threads} "
        "--out {output} {params.segment} > {log} 2>&1"


# A training longer than its partition's time limit: the segment jobs of its chain (resources.smk).
use rule train_box_labeler as train_box_labeler_segment with:
    output:
        segment_output(BOX_LABELER),
    log:
        f"logs/detection/labeler_{{platform}}.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/detection/labeler_{{platform}}.part{{part}}of{{parts}}.tsv"


rule pseudo_box:
    """Pseudo-boxes (Pi3DET infos) for one shard of a platform's generated scans."""
    input:
        labeler=lambda w: f"{DET}/{label_platform(w.label)}/labeler.pt",
        samples=f"{DATA}/samples/{{label}}/shard_{{shard}}",
    output:
        directory(f"{PSEUDO_BOXES}/{{label}}/shard_{{shard}}"),
    wildcard_constraints:
        shard=r"\d+",
        label="|".join(domain_label(p) for p in ("drone", "quadruped") if p in DOMAIN_NAMES),
    params:
        settings=lambda w: det_settings("labeler"),
        code=code("pseudo-box"),
    log:
        f"logs/detection/pseudo_boxes/{{label}}_{{shard}}.log",
    benchmark:
        f"benchmarks/out/detection/pseudo_boxes/{{label}}_{{shard}}.tsv"
    conda:
        ENV
    threads: 1
    priority: GDA_CHAIN_PRIORITY
    resources:
        **job_resources("pseudo_box"),
    shell:
        "omnilidar pseudo-box --labeler {input.labeler} --samples {input.samples} --settings {params.settings:q} "
        "--threads {threads} --out {output} > {log} 2>&1"


rule train_detector_real:
    """Supervised-only detection run: the real label subset alone, from scratch."""
    input:
        index=f"{DATA}/index/pi3det.json",
        model=lambda w: detector_yaml(w.detector),
        previous=previous_segment("train_detector_real", DETECTOR_REAL_RUN),
    output:
        DETECTOR_REAL_RUN,
    wildcard_constraints:
        platform=PI3DET_PLATFORMS,
        detector=DETECTOR_NAMES,
        pct=r"\d+",
    params:
        settings=lambda w: det_settings("schedule", "augmentation", detector=w.detector),
        seed=config["seed"],
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        code=code("train-detector"),
    log:
        f"logs/detection/train/{{platform}}_{{detector}}_{{pct}}pct_real.log",
    benchmark:
        f"benchmarks/out/detection/train/{{platform}}_{{detector}}_{{pct}}pct_real.tsv"
    conda:
        ENV
    threads: 1
    resources:
        **job_resources("train_detector_real"),
    shell:
        "omnilidar train-detector --detector {wildcards.detector} --platform {wildcards.platform} "
        "--index {input.index} --percent {wildcards.pct} --model-config {input.model} "
        "--settings {params.settings:q} --seed {params.seed} --work-dir {params.work_dir} --threads {threads} "
        "--out {output} {params.segment} > {log} 2>&1"


# A training longer than its partition's time limit: the segment jobs of its chain (resources.smk).
use rule train_detector_real as train_detector_real_segment with:
    output:
        segment_output(DETECTOR_REAL_RUN),
    log:
        f"logs/detection/train/{{platform}}_{{detector}}_{{pct}}pct_real.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/detection/train/{{platform}}_{{detector}}_{{pct}}pct_real.part{{part}}of{{parts}}.tsv"


rule train_detector_gda:
    """GDA detection run: the real label subset plus the platform's generated scans with the
    labeler's pseudo-boxes, from scratch; the mixing is configured and recorded."""
    input:
        index=f"{DATA}/index/pi3det.json",
        model=lambda w: detector_yaml(w.detector),
        samples=lambda w: domain_sample_shards(w.platform),
        pseudo=lambda w: pseudo_box_shards(w.platform),
        previous=previous_segment("train_detector_gda", DETECTOR_GDA_RUN),
    output:
        DETECTOR_GDA_RUN,
    wildcard_constraints:
        platform=PI3DET_PLATFORMS,
        detector=DETECTOR_NAMES,
        pct=r"\d+",
    params:
        settings=lambda w: det_settings("schedule", "augmentation", "mixing", detector=w.detector),
        seed=config["seed"],
        work_dir=lambda w, output: job_work_dir(output[0]),
        segment=segment_flag,
        code=code("train-detector"),
    log:
        f"logs/detection/train/{{platform}}_{{detector}}_{{pct}}pct_gda.log",
    benchmark:
        f"benchmarks/out/detection/train/{{platform}}_{{detector}}_{{pct}}pct_gda.tsv"
    conda:
        ENV
    threads: 1
    resources:
        **job_resources("train_detector_gda"),
    shell:
        "omnilidar train-detector --detector {wildcards.detector} --platform {wildcards.platform} "
        "--index {input.index} --percent {wildcards.pct} --model-config {input.model} "
        "--samples {input.samples} --pseudo-boxes {input.pseudo} "
        "--settings {params.settings:q} --seed {params.seed} --work-dir {params.work_dir} --threads {threads} "
        "--out {output} {params.segment} > {log} 2>&1"


# A training longer than its partition's time limit: the segment jobs of its chain (resources.smk).
use rule train_detector_gda as train_detector_gda_segment with:
    output:
        segment_output(DETECTOR_GDA_RUN),
    log:
        f"logs/detection/train/{{platform}}_{{detector}}_{{pct}}pct_gda.part{{part}}of{{parts}}.log",
    benchmark:
        f"benchmarks/out/detection/train/{{platform}}_{{detector}}_{{pct}}pct_gda.part{{part}}of{{parts}}.tsv"


rule evaluate_detector:
    """KITTI 3D / BEV AP (R11, R40) at IoU 0.5 and recall of one detector (or the labeler)
    on the platform's val frames."""
    input:
        checkpoint=f"{DET}/{{platform}}/{{run}}.pt",
        index=f"{DATA}/index/pi3det.json",
    output:
        f"{DET}/{{platform}}/{{run}}.val.json",
    wildcard_constraints:
        platform=PI3DET_PLATFORMS,
        run=rf"(({DETECTOR_NAMES})_\d+pct_(real|gda))|labeler",
    params:
        settings=lambda w: det_settings("evaluation"),
        code=code("evaluate-detector"),
    log:
        f"logs/detection/evaluate/{{platform}}_{{run}}.log",
    benchmark:
        f"benchmarks/out/detection/evaluate/{{platform}}_{{run}}.tsv"
    conda:
        ENV
    threads: 1
    resources:
        **job_resources("evaluate_detector"),
    shell:
        "omnilidar evaluate-detector --checkpoint {input.checkpoint} --index {input.index} --split val "
        "--settings {params.settings:q} --threads {threads} --out {output} > {log} 2>&1"


rule pi3det_result:
    """Voxel R-CNN and PV-RCNN on a Pi3DET platform's label subset: supervised-only vs GDA,
    with the box labeler's own val AP."""
    input:
        evaluations=lambda w: [f"{det_run(w.platform, d, w.pct, r)}.val.json"
                               for d in PI3DET_EXP["detectors"] for r in ("real", "gda")],
        labeler=f"{DET}/{{platform}}/labeler.val.json",
        pseudo=lambda w: pseudo_box_shards(w.platform),
    output:
        json="results/pi3det_{platform}_{pct}pct.json",
        figure="results/figures/pi3det_{platform}_{pct}pct.png",
        table="results/tables/pi3det_{platform}_{pct}pct.html",
    wildcard_constraints:
        platform=PI3DET_PLATFORMS,
        pct=r"\d+",
    params:
        experiment=lambda w: f"pi3det_{w.platform}_{w.pct}pct",
        settings=lambda w: json.dumps(DET_SECTION, sort_keys=True),
        seed=config["seed"],
        data_source=data_source("pi3det"),
        code=result_code("pi3det-result"),
    log:
        "logs/detection/pi3det_{platform}_{pct}pct.log",
    benchmark:
        "benchmarks/out/detection/pi3det_{platform}_{pct}pct.tsv"
    conda:
        ENV
    resources:
        **job_resources("pi3det_result"),
    shell:
        with_table("omnilidar pi3det-result --experiment {params.experiment} --platform {wildcards.platform} "
        "--percent {wildcards.pct} --settings {params.settings:q} --seed {params.seed} "
        "--data-source {params.data_source:q} --evaluations {input.evaluations} "
        "--labeler-evaluation {input.labeler} --pseudo-boxes {input.pseudo} "
        "--out {output.json} --figure {output.figure} > {log} 2>&1")


PI3DET_RESULTS = expand("results/pi3det_{platform}_{pct}pct.json", platform=PI3DET_EXP["platforms"],
                        pct=PI3DET_EXP["percents"])


rule pi3det_summary:
    """Car AP against the real-label fraction over every Pi3DET target (supervised-only, GDA, labeler)."""
    input:
        PI3DET_RESULTS,
    output:
        figure="results/figures/pi3det_label_fractions.png",
        table="results/pi3det_summary.json",
    params:
        code=code("pi3det-summary"),
    log:
        "logs/detection/pi3det_summary.log",
    conda:
        ENV
    resources:
        **job_resources("pi3det_result"),
    shell:
        "omnilidar pi3det-summary {input} --figure {output.figure} --out {output.table} > {log} 2>&1"


rule detection:
    """Every Pi3DET detection target and their label-fraction figure."""
    input:
        PI3DET_RESULTS,
        rules.pi3det_summary.output,
