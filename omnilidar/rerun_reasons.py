"""Why a job reruns, in words: which settings, code files, inputs and package versions changed.

Snakemake's dry run says *that* a job's params changed (``before: '...' now: '...'``); this
module says *what*: a settings JSON is compared key by key (``downstream.max_voxels: 80000 ->
10000``), a stage's code hash through the code manifests the workflow records when it computes
them (:func:`record_code_manifest`, one file per hash under ``.snakemake/omnilidar/code``), so a
hash change names the files whose content changed, and package versions key by key.

Stdlib only: the Snakefile imports :func:`record_code_manifest` at parse time.
"""

from __future__ import annotations

import ast
import json
import os
import re
from pathlib import Path

MANIFEST_DIR = Path(".snakemake") / "omnilidar" / "code"
_CODE = re.compile(r"^([0-9a-f]{16})(?: (\{.*\}))?$", re.S)


def record_code_manifest(digest: str, manifest: dict, workdir: Path = Path(".")) -> None:
    """Keep the per-file hashes behind a code hash (once per hash; never fails a run)."""
    path = workdir / MANIFEST_DIR / f"{digest[:16]}.json"
    if path.exists():
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")  # cluster jobs parse the workflow at the same time
        tmp.write_text(json.dumps(manifest, sort_keys=True))
        tmp.replace(path)
    except OSError:
        pass


def flatten_settings(value, prefix: str = "") -> dict:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (an empty mapping stays as its own value)."""
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            out.update(flatten_settings(v, f"{prefix}.{k}" if prefix else str(k)))
        return out or {prefix: {}}
    return {prefix: value}


def settings_changes(before: dict, now: dict, prefix: str = "") -> list[str]:
    """``key: old -> new`` for every setting that differs (``(absent)`` where one side lacks it)."""
    a, b = flatten_settings(before, prefix), flatten_settings(now, prefix)
    out = []
    for key in sorted(a.keys() | b.keys()):
        old, new = a.get(key, "(absent)"), b.get(key, "(absent)")
        if old != new:
            out.append(f"setting {key}: {json.dumps(old) if old != '(absent)' else old} -> "
                       f"{json.dumps(new) if new != '(absent)' else new}")
    return out


def _manifest(digest: str, workdir: Path) -> dict | None:
    path = workdir / MANIFEST_DIR / f"{digest}.json"
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def code_changes(before: str, now: str, workdir: Path = Path(".")) -> list[str]:
    """What moved a code param (``<hash>`` or ``<hash> {package versions}``) from ``before`` to ``now``."""
    mb, mn = _CODE.match(before), _CODE.match(now)
    out = []
    if mb.group(1) != mn.group(1):
        old, new = _manifest(mb.group(1), workdir), _manifest(mn.group(1), workdir)
        if old is None or new is None:
            out.append(f"code {mb.group(1)} -> {mn.group(1)} (no record of the files behind "
                       f"{'the old' if old is None else 'the new'} hash)")
        else:
            for f in sorted(old.keys() | new.keys()):
                if f not in old:
                    out.append(f"code {f}: now part of the stage")
                elif f not in new:
                    out.append(f"code {f}: no longer part of the stage")
                elif old[f] != new[f]:
                    out.append(f"code {f} changed")
    if (mb.group(2) or "") != (mn.group(2) or ""):
        vb, vn = json.loads(mb.group(2) or "{}"), json.loads(mn.group(2) or "{}")
        out += [f"package {k}: {vb.get(k)} -> {vn.get(k)}" for k in sorted(vb.keys() | vn.keys()) if vb.get(k) != vn.get(k)]
    return out


def _as_json(text: str):
    try:
        doc = json.loads(text)
    except ValueError:
        return None
    return doc if isinstance(doc, dict) else None


def params_changes(before: list[str], now: list[str], workdir: Path = Path(".")) -> list[str]:
    """Pairs the changed params of one job (settings JSON with settings JSON, code hash with code
    hash, the rest in order) and says what changed in each pair."""
    kinds = {"settings": lambda v: _as_json(v) is not None, "code": lambda v: bool(_CODE.match(v))}
    out = []
    rest_b, rest_n = list(before), list(now)
    for kind, test in kinds.items():
        bs, ns = [v for v in rest_b if test(v)], [v for v in rest_n if test(v)]
        for b, n in zip(bs, ns):
            rest_b.remove(b)
            rest_n.remove(n)
            out += settings_changes(_as_json(b), _as_json(n)) if kind == "settings" else code_changes(b, n, workdir)
    out += [f"param {b!r} -> {n!r}" for b, n in zip(rest_b, rest_n)]
    out += [f"param {b!r} dropped" for b in rest_b[len(rest_n):]] + [f"param {n!r} added" for n in rest_n[len(rest_b):]]
    return out


_PARAMS = re.compile(r"Params have changed since last execution:.*?before: (.*) now: (.*)$")


def reason_in_words(reason: str, workdir: Path = Path(".")) -> list[str]:
    """One job's dry-run reason as a list of changes in words (the reason itself where it is
    already words: missing outputs, updated inputs, forced runs)."""
    m = _PARAMS.search(reason)
    if not m:
        return [reason.strip()]
    try:
        before, now = ast.literal_eval(f"[{m.group(1)}]"), ast.literal_eval(f"[{m.group(2)}]")
    except (ValueError, SyntaxError):
        return [reason.strip()]
    words = params_changes([str(v) for v in before], [str(v) for v in now], workdir)
    other = reason[: m.start()].strip().rstrip(";").strip()
    return ([other] if other else []) + (words or ["params changed (values equal after parsing)"])


_BLOCK = re.compile(r"^(?:local)?rule (\w+):\n(.*?)(?=^\[|^(?:local)?rule \w+:|\Z)", re.M | re.S)


def jobs_from_dry_run(text: str) -> list[dict]:
    """(rule, output, wildcards, reason) of every job a Snakemake dry run printed."""
    jobs = []
    for m in _BLOCK.finditer(text):
        fields = dict(re.findall(r"^    (\w+): (.*)$", m.group(2), re.M))
        if "reason" in fields:
            jobs.append({"rule": m.group(1), "output": fields.get("output", ""), "wildcards": fields.get("wildcards", ""),
                         "reason": fields["reason"]})
    return jobs
