"""Every Snakemake command that README and docs/ show runs as written, as a dry run where it
would train, in a fresh copy of the workflow; every `omnilidar` command line they show is accepted
(it stops only on the inputs a fresh clone has not made yet, with one clear error)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from workflow_helpers import ROOT, copy_workflow, snakemake

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# What a reader fills in for the placeholders.
PLACEHOLDERS = {"<target>": "results/semkitti_1pct.json", "<your account>": "testacct", "<account>": "testacct"}


def _commands(text: str) -> list[tuple[str, str | None]]:
    """(command, the page's last YAML block before it) of every shell line in fenced bash blocks and
    every inline `snakemake ...`; `\\` continuations joined, comments and prompts dropped."""
    found = []
    yaml_block = None
    for m in re.finditer(r"```(\w*)\n(.*?)```|`(snakemake [^`]+)`", text, re.S):
        if m.group(3):
            found.append((" ".join(m.group(3).split()), yaml_block))
            continue
        if m.group(1) == "yaml":
            yaml_block = m.group(2)
        if m.group(1) not in ("bash", "sh"):
            continue
        for line in m.group(2).replace("\\\n", " ").splitlines():
            line = " ".join(line.split(" #")[0].split())
            if line and not line.startswith("#"):
                found.append((line, yaml_block))
    return found


def _all_commands() -> list[tuple[str, str, str | None]]:
    out = []
    for page in PAGES:
        for cmd, yaml_block in _commands(page.read_text()):
            for key, value in PLACEHOLDERS.items():
                cmd = cmd.replace(key, value)
            out.append((page.name, cmd, yaml_block))
    return out


def _brace_expanded(args: list[str]) -> list[str]:
    """Brace expansion as the shell does it (``shard_{0,1}``)."""
    out = []
    for a in args:
        m = re.match(r"(.*?)\{([^}]*,[^}]*)\}(.*)", a)
        out += _brace_expanded([m.group(1) + part + m.group(3) for part in m.group(2).split(",")]) if m else [a]
    return out


def _snakemake_part(cmd: str) -> list[str] | None:
    """The snakemake invocation of a line (the last step of an `&&` chain), as arguments."""
    step = cmd.split("&&")[-1].strip()
    return _brace_expanded(shlex.split(step)[1:]) if step.startswith("snakemake") else None


# Blocks that start a cluster first: tests/test_slurm_real.py runs the same script, profile and
# configuration on a real single-node SLURM.
ON_A_LIVE_CLUSTER = ("--slurm-status-command squeue --configfile config/test.yaml /tmp/cluster.yaml",)


SNAKEMAKE = sorted({(page, cmd, y) for page, cmd, y in _all_commands()
                    if _snakemake_part(cmd) and not any(live in cmd for live in ON_A_LIVE_CLUSTER)}, key=str)
OMNILIDAR = sorted({(page, cmd) for page, cmd, _ in _all_commands() if cmd.startswith("omnilidar ")})


def test_the_pages_show_commands_to_check():
    pages = {page for page, _, _ in SNAKEMAKE}
    assert "README.md" in pages and "cluster.md" in pages and len(SNAKEMAKE) >= 10
    assert OMNILIDAR


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return copy_workflow(tmp_path_factory.mktemp("docs_commands"))


@pytest.mark.parametrize("page,cmd,yaml_block", SNAKEMAKE, ids=[f"{p}: {c}" for p, c, _ in SNAKEMAKE])
def test_snakemake_command_runs_as_written(workdir, tmp_path, page, cmd, yaml_block):
    args = _snakemake_part(cmd)
    for i, arg in enumerate(args):
        # A config file the page has the reader write: the page's YAML block before the command.
        if arg.endswith(".yaml") and not (workdir / arg).exists() and not Path(arg).is_absolute():
            assert yaml_block, f"{page}: {arg} is neither shipped nor shown"
            if "../shared/" in yaml_block and not (ROOT.parent / "shared").is_dir():
                pytest.skip(f"{arg} lists real scans from ../shared, which this clone has not beside it")
            args[i] = str(tmp_path / arg)
            Path(args[i]).write_text(yaml_block.replace("../shared/", f"{ROOT.parent}/shared/"))
    trains = not any(a in args for a in ("--unlock", "--report", "-n", "--dry-run"))
    env = {"SBATCH_ACCOUNT": "testacct"}
    out = snakemake(workdir, *(["--dry-run"] if trains else []), *args, check=False, env=env)
    assert out.returncode == 0, f"{page}: `{cmd}` failed:\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}"


@pytest.mark.parametrize("page,cmd", OMNILIDAR, ids=[f"{p}: {c[:60]}" for p, c in OMNILIDAR])
def test_omnilidar_command_line_is_accepted(workdir, page, cmd):
    expanded = _brace_expanded(shlex.split(cmd)[1:])
    env = dict(os.environ, PYTHONPATH=str(workdir))
    out = subprocess.run([sys.executable, "-m", "omnilidar.cli", *expanded], cwd=workdir, env=env,
                         capture_output=True, text=True)
    text = out.stdout + out.stderr
    assert "usage:" not in text and "unrecognized arguments" not in text, f"{page}: `{cmd}`:\n{text[-1500:]}"
    if out.returncode != 0:  # only for want of what a fresh clone has not made: one line naming it
        assert re.search(r"data/(samples|pseudo_boxes|pseudo_labels)/\S+", text), f"{page}: `{cmd}`:\n{text[-1500:]}"
        assert "Traceback" not in text, text
