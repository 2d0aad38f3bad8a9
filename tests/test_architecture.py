"""The structure docs/architecture.md describes, held against the code: the layers of the
packages (no import from a higher layer, hence no cycle between packages), no import
cycle between modules, functions and classes of a size one can read, and every SPEC
effect in the one registry.  Imports inside functions count as imports here: a cycle
hidden in a function-level import is still a cycle."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: the layers of docs/architecture.md, lowest first: a package may import only from its
#: own package and from packages of lower layers
LAYERS = (
    ("tacest", "tacest.errors", "tacest.constants", "tacest.interrupt"),
    ("tacest.geometry", "tacest.provenance", "tacest.linear_solver", "tacest.parallel"),
    ("tacest.io", "tacest.dynamics"),
    ("tacest.model", "tacest.sim", "tacest.sensors", "tacest.evaluation", "tacest.view"),
    ("tacest.estimation", "tacest.sim3d"),
    ("tacest.information", "tacest.export"),
    ("tacest.planning",),
    ("tacest.diagnosis",),
    ("tacest.dims",),
    ("tacest.batch",),
    ("tacest.cli",),
    ("tacest.__main__",),
)
#: functions longer than this many lines (with docstring and comments) need a written
#: reason (none today); a screen and a half of code is what one can hold at once
MAX_FUNCTION_LINES = 120
#: classes longer than this need a written reason (none today)
MAX_CLASS_LINES = 500


def _modules():
    """{module name: path} of tacest and its CLI (installed as tacest.cli)."""
    out = {}
    for base, pkg in (("tacest", "tacest"), ("cli", "tacest.cli")):
        for p in sorted((ROOT / base).rglob("*.py")):
            rel = p.relative_to(ROOT / base).with_suffix("")
            parts = [x for x in rel.parts if x != "__init__"]
            out[".".join([pkg, *parts]) if parts else pkg] = p
    return out


def _imports(path: Path, modules) -> set:
    """Modules of tacest that ``path`` imports, at any level of the file."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        found |= {n for n in names if n in modules}
    return found


def _package(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 else module


def _layer(package: str) -> int:
    for k, names in enumerate(LAYERS):
        if package in names:
            return k
    raise AssertionError(f"package {package} is in no layer of tests/test_architecture.py (and "
                         "docs/architecture.md): place it")


def _graph():
    modules = _modules()
    return {m: _imports(p, modules) - {m} for m, p in modules.items()}


def test_packages_import_only_from_lower_layers():
    bad = []
    for m, deps in _graph().items():
        a = _package(m)
        for d in deps:
            b = _package(d)
            if a != b and _layer(b) >= _layer(a):
                bad.append(f"{m} imports {d} ({b} is not below {a})")
    assert not bad, "\n".join(sorted(bad))


def test_no_import_cycle_between_modules():
    graph = _graph()
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_functions_and_classes_have_a_readable_size():
    long = []
    for m, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                limit = MAX_FUNCTION_LINES
            elif isinstance(node, ast.ClassDef):
                limit = MAX_CLASS_LINES
            else:
                continue
            n = node.end_lineno - node.lineno + 1
            if n > limit:
                long.append(f"{m}.{node.name}: {n} lines (limit {limit})")
    assert not long, "\n".join(long)


def test_every_spec_effect_is_in_the_one_registry():
    from tacest.model.registry import NONE, REGISTRY
    from tacest.sim.effects import EFFECT_NAMES

    assert set(EFFECT_NAMES) - {NONE} <= set(REGISTRY)
    # the registry's extensions are documented, 3-D effects of the model
    assert set(REGISTRY) - set(EFFECT_NAMES) == {"edge_radius", "ground_offset"}


@pytest.mark.parametrize("dim", [2, 3])
def test_every_model_effect_has_parameters_with_priors_inside_their_bounds(dim):
    from tacest.model.registry import REGISTRY, model_effect_names

    for name in model_effect_names(dim):
        pars = REGISTRY[name].parameters(4, dim)
        assert pars, name
        for p in pars:
            assert p.lower <= p.centre <= p.upper and p.sigma > 0, (name, p)
            assert p.start is None or p.lower <= p.start <= p.upper, (name, p)
