# The workflow report (`snakemake --report report.html`): the table and figure of every result
# made so far. They are flagged for the report on the `all` rule through their folders, not on
# the rules that write them: a flagged output of a job that has not run stops the report, and
# naming a result's files on `all` would schedule (or rerun) that result. So the report works
# after any run and gathers exactly what exists.

REPORT_TABLES = "results/tables"
REPORT_FIGURES = "results/figures"

# Result name pattern -> (report category, caption file in workflow/report/).
REPORT_SECTIONS = (
    (r"data_summary", "Data", "data_summary.rst"),
    (r"domain_fidelity", "Domains", "domain_fidelity.rst"),
    (r"effects_tradeoff", "Domains", "effects_tradeoff.rst"),
    (r"semkitti_\d+pct|semkittic|semanticstf|nusc_beam32_\d+pct", "Segmentation", "segmentation.rst"),
    (r"gda_curve", "Accuracy vs time", "gda_curve.rst"),
    (r"gda_decomposition", "Segmentation", "gda_decomposition.rst"),
    (r"tradeoff", "Accuracy vs time", "tradeoff.rst"),
    (r"generation_quality", "Generation", "generation_quality.rst"),
    (r"ablation", "Generation", "ablation.rst"),
    (r"kitti360_generation", "Generation", "kitti360_generation.rst"),
    (r"generator_evidence", "Generation", "generator_evidence.rst"),
    (r"pi3det_\w+_\d+pct", "Detection", "detection.rst"),
)


def report_section(name):
    """(category, caption file) of the result called ``name`` (Other, None when unknown)."""
    for pattern, category, caption in REPORT_SECTIONS:
        if re.fullmatch(pattern, name):
            return category, caption
    return "Other", None


def report_captions():
    """Caption text of every result whose table or figure exists, by name (for result.rst)."""
    captions = {}
    for folder in (REPORT_TABLES, REPORT_FIGURES):
        for entry in sorted(os.listdir(folder)) if os.path.isdir(folder) else ():
            name = os.path.splitext(entry)[0]
            caption = report_section(name)[1]
            if caption is not None:
                with open(os.path.join(workflow.basedir, "workflow", "report", caption)) as fh:
                    captions[name] = fh.read()
    return captions


# `snakemake --report` builds the DAG of its target (`all` by default) and warns "Missing metadata"
# for every output of every job in it, made or not. While reporting, `all` therefore names only
# the default results that exist, so the report speaks of what was made.
REPORTING = any(arg == "--report" or arg.startswith("--report=") for arg in sys.argv)


def default_results(*paths):
    """The default target's results; while reporting, only those that exist."""
    return [p for p in paths if not REPORTING or os.path.exists(p)]


def report_files():
    """The folders of result tables and figures, flagged for the report, where they exist."""
    flagged = []
    for folder, suffix, kind in ((REPORT_TABLES, "html", "Tables"), (REPORT_FIGURES, "png", "Figures")):
        if os.path.isdir(folder):
            flagged.append(report(folder, patterns=[f"{{name}}.{suffix}"], subcategory=kind,
                                  category=lambda w: report_section(w.name)[0],
                                  caption=os.path.join(workflow.basedir, "workflow", "report", "result.rst")))
    return flagged
