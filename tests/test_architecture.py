"""The package layout keeps the data flow (README, "Architecture"): no module imports from a later stage, no
module imports another module's private names, the imports form no circle (in `src/` and among `scripts/`), and
`src/jaxci/` holds at most `MAX_FLAT` modules outside its folders. Read from the source (ast), so imports inside
functions count too; those under ``if TYPE_CHECKING:`` do not (they never run)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
SCRIPTS = ROOT / "scripts"

#: Stage of each module (longest matching prefix): a module may import its own stage and the ones before it.
STAGES = {
    "jaxci.errors": 0, "jaxci.runtime": 0, "jaxci.cells": 0, "jaxci.native": 0, "jaxci._ckernels": 0,
    "jaxci.mesh": 1, "jaxci.io": 1,
    "jaxci.geometry": 2,
    "jaxci.metrics": 3,
    "jaxci.optim": 4,
    "jaxci.interface": 5,
    "jaxci.experiments": 6,
    "jaxci.cli": 7, "jaxci.__main__": 7,
    "jaxci": 8,  # the public API re-exports every stage
}

#: At most this many modules directly in `src/jaxci/` (the public API, ``python -m jaxci``, the errors, the C
#: kernels' loader and the cell tables they share with every stage); every other module lives in its stage's folder.
MAX_FLAT = 10

#: Import circles kept on purpose, each with its reason (none: the model converts a meshio.Mesh itself,
#: `jaxci.mesh.convert`, instead of importing the formats).
KNOWN_CIRCLES: set = set()


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in (SRC / "jaxci").rglob("*.py")}


def _stage(module: str) -> int:
    while module not in STAGES:
        module = module.rpartition(".")[0]
    return STAGES[module]


def _imports(name: str, path: Path):
    """``(imported module, imported name or None, line)`` for every import of a jaxci module in `path`."""
    tree = ast.parse(path.read_text())
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for b in node.body for n in ast.walk(b))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("jaxci"):
                    yield a.name, None, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("jaxci"):
                continue
            for a in node.names:
                sub = f"{target}.{a.name}"
                yield (sub, None, node.lineno) if sub in MODULES or a.name == "_ckernels" else (target, a.name,
                                                                                                 node.lineno)


EDGES = {name: list(_imports(name, path)) for name, path in MODULES.items()}


def test_the_stages_cover_every_module():
    assert all(_stage(m) < STAGES["jaxci"] or m == "jaxci" for m in MODULES), "a module outside every stage"


@pytest.mark.parametrize("name", sorted(MODULES))
def test_no_module_imports_from_a_later_stage(name):
    bad = [f"line {line}: {target}" for target, what, line in EDGES[name]
           if _stage(target) > _stage(name) and not (target == "jaxci" and what == "__version__")]
    assert not bad, f"{name} (stage {_stage(name)}) imports from a later stage: {bad}"


@pytest.mark.parametrize("name", sorted(MODULES))
def test_no_private_name_is_imported_from_another_module(name):
    bad = [f"line {line}: {target}.{what}" for target, what, line in EDGES[name]
           if what is not None and what.startswith("_") and not what.startswith("__")]
    assert not bad, f"{name} imports private names of other modules: {bad}"


def _circles(graph: dict[str, set[str]], known=frozenset()) -> list[tuple]:
    """Every circle of `graph` (module -> the modules it imports), apart from the pairs in `known`: pairs that
    import each other, and longer circles (a module that reaches itself)."""
    circles = []
    for a in graph:
        for b in graph[a]:
            if a < b and a in graph.get(b, ()) and frozenset({a, b}) not in known:
                circles.append((a, b))
    state: dict[str, int] = {}

    def visit(m, stack):
        state[m] = 1
        for t in graph[m]:
            if frozenset({m, t}) in known:
                continue
            if state.get(t) == 1:
                circles.append(tuple(stack[stack.index(t):] + [t]))
            elif t not in state:
                visit(t, stack + [t])
        state[m] = 2

    for m in sorted(graph):
        if m not in state and m != "jaxci":
            visit(m, [m])
    return sorted(set(circles))


def test_the_imports_form_no_circle():
    graph = {m: {t for t, _, _ in EDGES[m] if t in MODULES and t != m} for m in MODULES}
    assert not _circles(graph, KNOWN_CIRCLES), f"import circles: {_circles(graph, KNOWN_CIRCLES)}"


def test_the_scripts_import_each_other_in_no_circle():
    """`scripts/` imports its own modules by name (the folder on ``sys.path``): those imports form no circle."""
    names = {p.stem for p in SCRIPTS.glob("*.py")}
    graph = {}
    for name in names:
        tree = ast.parse((SCRIPTS / f"{name}.py").read_text())
        found = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                found.update(a.name.partition(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                found.add(node.module.partition(".")[0])
        graph[name] = (found & names) - {name}
    assert any(graph.values()), "no script imports another: the check reads nothing"
    assert not _circles(graph), f"import circles among scripts/: {_circles(graph)}"


def test_src_jaxci_has_at_most_max_flat_modules():
    flat = sorted(p.name for p in (SRC / "jaxci").glob("*.py"))
    assert len(flat) <= MAX_FLAT, f"{len(flat)} modules directly in src/jaxci/ (at most {MAX_FLAT}): {flat}"
