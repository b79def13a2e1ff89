"""Which datasets a result used, and whether each was real or generated.

Every results JSON carries ``data_source``: ``{dataset: {"root": path, "kind":
"real" | "synthetic"}}``, one entry per dataset the result depends on (a
synthetic dataset's root is where the synthetic world wrote it). The workflow
builds it from the config (``rules/common.smk``) and passes it to the result
commands as ``--data-source JSON``.

Stdlib only: the Snakefile imports this module at parse time.
"""

from __future__ import annotations

import argparse
import json

KINDS = ("real", "synthetic")


def record(root: str, synthetic: bool) -> dict:
    return {"root": str(root), "kind": "synthetic" if synthetic else "real"}


def parse(text: str) -> dict:
    """``--data-source`` JSON, checked (an argparse type: a bad value is one usage error)."""
    try:
        value = json.loads(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"not JSON: {err}") from None
    if not isinstance(value, dict) or not value:
        raise argparse.ArgumentTypeError("expected a non-empty object {dataset: {root, kind}}")
    for name, rec in value.items():
        if not isinstance(rec, dict) or set(rec) != {"root", "kind"} or rec["kind"] not in KINDS \
                or not isinstance(rec["root"], str):
            raise argparse.ArgumentTypeError(
                f"entry {name!r} must be {{\"root\": path, \"kind\": \"real\" or \"synthetic\"}}, got {rec!r}")
    return value


def mixed(sources: dict) -> bool:
    """True when ``sources`` holds both real and synthetic datasets."""
    return len({rec["kind"] for rec in sources.values()}) > 1


def describe(sources: dict, roots: bool = True) -> str:
    """``real semantickitti (/data/kitti), synthetic pi3det (data/synthetic/pi3det)``."""
    parts = []
    for kind in KINDS:
        names = [f"{n} ({r['root']})" if roots else n for n, r in sorted(sources.items()) if r["kind"] == kind]
        if names:
            parts.append(f"{kind} {', '.join(names)}")
    return ", ".join(parts)


def configured_scans(paths: list) -> dict:
    """The effect reports' source: the real scan files named in the config."""
    import os

    root = os.path.commonpath([os.path.abspath(p) for p in paths]) if paths else ""
    return {"configured_scans": record(root, synthetic=False)}
