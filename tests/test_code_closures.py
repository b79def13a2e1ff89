"""Rules that keep per-stage code hashes exact (omnilidar.provenance).

A stage's hash covers the modules it imports and the data files they declare in
``DATA_FILES``. These tests scan the package so that a new package ``__init__``
re-export or a new data file read cannot widen or escape a hash unnoticed.
"""

from __future__ import annotations

import ast
import fnmatch
from pathlib import Path

import pytest

from omnilidar import provenance

PACKAGE_DIR = provenance.PACKAGE_DIR
ROOT = PACKAGE_DIR.parent
MODULES = sorted(p for p in PACKAGE_DIR.rglob("*.py") if "__pycache__" not in p.parts)

# Files of the checkout that package code could read at run time (not tests or docs).
DATA_CANDIDATES = sorted(
    p.relative_to(ROOT).as_posix()
    for folder in ("omnilidar", "workflow", "config")
    for p in (ROOT / folder).rglob("*")
    if p.is_file() and p.suffix not in (".py", ".pyc") and "__pycache__" not in p.parts
)

# Modules that locate files themselves, with the reason their reads need no declaration.
UNDECLARED_READS = {
    "omnilidar/config.py": "reads the schema its caller names (the callers declare it, see "
                           "test_validations_name_a_declared_schema); the whole-config schema is "
                           "for the Snakefile and tests",
    "omnilidar/provenance.py": "reads package sources and declared data files to hash them",
}


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _tree(path: Path) -> ast.Module:
    return provenance._strip_docstrings(ast.parse(path.read_text()))


def _declared(path: Path) -> set[str]:
    return set(provenance._declared(ast.parse(path.read_text()), "DATA_FILES", path))


@pytest.mark.parametrize("init", [p for p in MODULES if p.name == "__init__.py"], ids=_rel)
def test_package_inits_import_no_submodule_of_their_package(init):
    """Importing ``omnilidar.metrics.bev`` runs ``omnilidar/metrics/__init__.py``: if
    that imported ``frechet``, every user of any metric would depend on all of them."""
    imports, dispatched = provenance._imports(init, ast.parse(init.read_text()))
    inside = sorted(_rel(f) for f in imports | dispatched if f != init and f.is_relative_to(init.parent))
    assert not inside, f"{_rel(init)} imports modules of its own package: {inside}; import them where used"


def _file_names(tree: ast.Module):
    """(string, is_dynamic) for every string literal and f-string tail in a module."""
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            tail = node.values[-1] if node.values else None
            if isinstance(tail, ast.Constant) and isinstance(tail.value, str):
                yield tail.value, True
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            yield node.value, False


def _named_files(name: str, dynamic: bool) -> list[str]:
    if "\n" in name or "." not in name:
        return []
    if dynamic:
        return [p for p in DATA_CANDIDATES if p.endswith(name)]
    if any(c in name for c in "*?["):
        return [p for p in DATA_CANDIDATES if fnmatch.fnmatch(p, name) or fnmatch.fnmatch(p.rsplit("/", 1)[-1], name)]
    return [p for p in DATA_CANDIDATES if p == name or p.endswith("/" + name)]


def test_every_data_file_a_module_names_is_declared_next_to_it():
    """A string naming a file of the checkout (``"generator.schema.yaml"``) means the
    module reads it: it must be in the module's DATA_FILES, so that its content is
    part of the code hash of every stage that runs the module."""
    problems = []
    for path in MODULES:
        rel = _rel(path)
        if rel in UNDECLARED_READS:
            continue
        declared = _declared(path)
        tree = _tree(path)
        for name, dynamic in _file_names(tree):
            hits = _named_files(name, dynamic)
            if hits and (dynamic or any(c in name for c in "*?[")):
                problems.append(f"{rel}: {name!r} names files by pattern ({', '.join(hits)}); "
                                "name each file and declare it in DATA_FILES")
            elif hits and not declared & set(hits):
                problems.append(f"{rel}: reads {name!r} ({', '.join(hits)}) but DATA_FILES does not declare it")
        uses_file = any(isinstance(n, ast.Name) and n.id == "__file__" for n in ast.walk(tree))
        uses_resources = any(isinstance(n, (ast.Import, ast.ImportFrom)) and any(
            "importlib.resources" in (a.name if isinstance(n, ast.Import) else f"{n.module}.{a.name}")
            or (isinstance(n, ast.ImportFrom) and n.module == "pkgutil" and a.name == "get_data")
            for a in n.names) for n in ast.walk(tree))
        if (uses_file or uses_resources) and not declared:
            problems.append(f"{rel}: locates files next to the code (__file__ / importlib.resources) "
                            "but declares no DATA_FILES")
    assert not problems, "\n".join(problems)


def test_data_files_inside_the_package_are_declared_by_a_module():
    declared = set().union(*(_declared(p) for p in MODULES))
    inside = [p for p in DATA_CANDIDATES if p.startswith(f"{PACKAGE_DIR.name}/")]
    assert not [p for p in inside if p not in declared], "package data files nobody declares"


def test_declared_data_files_exist():
    for path in MODULES:
        for rel in _declared(path):
            assert (ROOT / rel).is_file(), f"{_rel(path)}: DATA_FILES names {rel}, which does not exist"


def test_validations_name_a_declared_schema():
    """config.validate reads the schema its caller names, so the caller declares it;
    the package never validates the whole config or asks for a section's defaults
    (schemas chosen at run time, which no declaration could follow)."""
    problems = []
    for path in MODULES:
        rel = _rel(path)
        if rel == "omnilidar/config.py":
            continue
        tree = ast.parse(path.read_text())
        from_config = {a.asname or a.name for n in ast.walk(tree)
                       if isinstance(n, ast.ImportFrom) and n.module == "omnilidar.config" for a in n.names}
        declared = {Path(f).name for f in _declared(path)}
        for call in ast.walk(tree):
            if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Name) and call.func.id in from_config):
                continue
            name = call.func.id
            if name in ("load_config", "section_defaults"):
                problems.append(f"{rel}:{call.lineno}: {name} (whole config / defaults) in package code")
            elif name in ("validate", "_load_schema"):
                args = call.args[1:2] if name == "validate" else call.args[:1]
                args += [k.value for k in call.keywords if k.arg == "schema_name"]
                schema = args[0] if args else None
                if not (isinstance(schema, ast.Constant) and isinstance(schema.value, str)):
                    problems.append(f"{rel}:{call.lineno}: {name} without a literal schema name")
                elif schema.value not in declared:
                    problems.append(f"{rel}:{call.lineno}: {name} reads {schema.value}, not in DATA_FILES")
    assert not problems, "\n".join(problems)
