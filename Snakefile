# OmniLiDAR GDA pipeline. Thin on purpose: configuration, validation, rule files.
# Every cluster job re-parses this file, so nothing heavy is imported here.
import os

from snakemake.utils import min_version

min_version("9.0")


# The embedded default: the working directory's config/config.yaml when it has one (a deployed
# copy to edit), else the workflow's own, so the workflow also runs from an empty directory.
configfile: "config/config.yaml" if os.path.exists("config/config.yaml") else f"{workflow.basedir}/config/config.yaml"


include: "rules/common.smk"
include: "rules/resources.smk"
include: "rules/report.smk"
include: "rules/data.smk"
include: "rules/domains.smk"
include: "rules/generator.smk"
include: "rules/evaluation_sets.smk"
include: "rules/evaluation.smk"
include: "rules/downstream.smk"
include: "rules/detection.smk"


# Jobs that only list files or assemble results (seconds of work): on a cluster they run on the
# submitting host instead of waiting in the queue (locally this changes nothing).
localrules:
    all,
    index_dataset,
    domains_index,
    make_subset,
    make_pool,
    make_heldout,
    semkitti_result,
    semkittic_result,
    nusc_beam32_result,
    semanticstf_result,
    gda_curve,
    gda_decomposition,
    gda_budget,
    pi3det_result,
    pi3det_summary,


onsuccess:
    record_versions()
    # Tell the user where the results are (the JSON files and their figures).
    import glob

    produced = sorted(glob.glob("results/*.json"))
    if produced:
        print("Results: " + ", ".join(produced) + " (figures in results/figures/)")


onerror:
    # The failed jobs' own error lines (one clear line per bad input) on the terminal.
    report_failed_jobs(log)


rule all:
    default_target: True
    input:
        default_results("results/semkitti_1pct.json", "results/data_summary.json"),
        report_files(),  # what `snakemake --report report.html` gathers: rules/report.smk
    params:
        captions=report_captions(),
