"""The package's import graph has layers and no circles.

Every import counts, also one inside a function (``omnilidar.provenance`` reads them all for the
code hashes): a lazy import may save start-up time, never hide an upward arrow or a circle.
"""

from __future__ import annotations

import ast

from omnilidar import provenance

# Bottom to top. A module may import its own unit and the units of layers below, never above.
LAYERS = (
    ("errors", "yaml_load", "dicts", "devices", "progress", "allocator"),
    ("manifest", "provenance", "config", "rerun_reasons"),
    ("geometry", "lidar", "sparse"),
    ("segnets",),  # MinkUNet / SPVCNN on the sparse engine
    ("io",),
    ("data", "data_source", "checkpoints"),
    ("interop",),  # other toolkits' checkpoint layouts -> our networks
    ("generator",),
    ("metrics",),
    ("domains",),
    ("downstream",),
    ("report",),
    ("commands",),
    ("cli",),
)
RANK = {unit: rank for rank, units in enumerate(LAYERS) for unit in units}


def _unit(path) -> str:
    rel = path.relative_to(provenance.PACKAGE_DIR)
    return rel.parts[0].removesuffix(".py") if len(rel.parts) > 1 or rel.name != "__init__.py" else ""


def _graph() -> dict:
    graph = {}
    for f in sorted(provenance.PACKAGE_DIR.rglob("*.py")):
        imports, dispatched = provenance._imports(f, ast.parse(f.read_text()))
        # A package's __init__ runs on import but imports no submodules (test_code_closures).
        graph[f] = {g for g in imports | dispatched if g.name != "__init__.py" and g != f}
    return graph


def test_every_unit_of_the_package_has_a_layer():
    units = {_unit(f) for f in provenance.PACKAGE_DIR.rglob("*.py")} - {""}
    assert not units - RANK.keys(), f"units with no layer in LAYERS: {sorted(units - RANK.keys())}"


def test_no_module_imports_one_from_a_layer_above_it():
    upward = [f"{f.relative_to(provenance.PACKAGE_DIR)} -> {g.relative_to(provenance.PACKAGE_DIR)}"
              for f, targets in _graph().items() for g in targets
              if _unit(f) and _unit(g) and RANK[_unit(g)] > RANK[_unit(f)]]
    assert not upward, "imports from a layer above:\n" + "\n".join(upward)


def test_no_import_circles_between_modules():
    graph = _graph()
    index, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(str(c.relative_to(provenance.PACKAGE_DIR)) for c in component))

    for v in graph:
        if v not in index:
            visit(v)
    assert not circles, f"import circles: {circles}"


def test_figures_are_saved_in_one_place():
    savers = sorted(str(f.relative_to(provenance.PACKAGE_DIR)) for f in provenance.PACKAGE_DIR.rglob("*.py")
                    if ".savefig(" in f.read_text())
    assert savers == ["io/figure.py"], savers
