"""omnilidar why: what changed since each job that would rerun last ran, in words."""

from __future__ import annotations

HELP = "say, per job that would rerun for TARGET, which settings, code files, inputs or package versions changed"


def add_arguments(parser) -> None:
    parser.add_argument("targets", nargs="*", help="Snakemake targets (default: the workflow's default target)")
    parser.add_argument("--configfile", nargs="+", default=[], help="config files, as given to Snakemake")
    parser.add_argument("--snakefile", default=None, help="the workflow's Snakefile (default: ./Snakefile)")


def run(args) -> int:
    import subprocess
    import sys
    from pathlib import Path

    from omnilidar.errors import InputError
    from omnilidar.rerun_reasons import jobs_from_dry_run, reason_in_words

    cmd = [sys.executable, "-m", "snakemake", "--dry-run", "--cores", "1"]
    if args.snakefile:
        cmd += ["--snakefile", args.snakefile]
    if args.configfile:
        cmd += ["--configfile", *args.configfile]
    out = subprocess.run([*cmd, "--", *args.targets], capture_output=True, text=True)
    text = out.stdout + out.stderr
    if out.returncode != 0:
        raise InputError(None, "the dry run failed:\n" + text[-2000:])
    jobs = jobs_from_dry_run(text)
    if not jobs:
        print("nothing to do: every output is up to date")
        return 0
    for job in jobs:
        where = f" ({job['wildcards']})" if job["wildcards"] else ""
        print(f"{job['rule']}{where} -> {job['output']}")
        for line in reason_in_words(job["reason"], Path(".")):
            print(f"    {line}")
    print(f"{len(jobs)} jobs would run")
    return 0
