"""The package's layering, checked on its import graph.

Data flows one way: a module imports only modules of its own layer or of lower
layers (function-local imports included), the graph of modules has no cycle,
and matplotlib is imported only by the output layer (figures) — the CLI alone
selects a backend.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "cpas_bayes"

# Lowest first. A module may import its own layer and any layer before it.
LAYERS = ("core", "physics", "data", "stats", "inference", "population", "loads", "outputs", "app")
MATPLOTLIB_LAYERS = {"outputs", "app"}
MAX_LINES = 600
# Modules allowed beyond MAX_LINES because they are one concept (say why here).
ONE_CONCEPT = {}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path):
    """(imported module, line) for every import in the file, relative ones resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            yield module, node.lineno
            for alias in node.names:  # "from cpas_bayes.x import module"
                yield f"{module}.{alias.name}", node.lineno


def _layer(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] != "cpas_bayes" or len(parts) < 2:
        return None
    return parts[1] if parts[1] in LAYERS else None


def _package_modules():
    return {_module_name(p): p for p in PACKAGE.rglob("*.py")}


MODULES = _package_modules()


def _graph():
    graph = {}
    for name, path in MODULES.items():
        graph[name] = {target for target, _ in _imports(path) if target in MODULES and target != name}
    return graph


def test_every_module_sits_in_a_layer():
    outside = [name for name in MODULES if name != "cpas_bayes" and _layer(name) is None and name != "cpas_bayes.__main__"]
    assert not outside, f"modules outside the layers {LAYERS}: {outside}"


def test_no_upward_imports():
    upward = []
    for name, path in MODULES.items():
        own = _layer(name)
        if own is None:
            continue
        for target, line in _imports(path):
            other = _layer(target)
            if other is not None and LAYERS.index(other) > LAYERS.index(own):
                upward.append(f"{path.relative_to(PACKAGE.parent)}:{line} ({own}) imports {target} ({other})")
    assert not upward, "upward imports:\n" + "\n".join(sorted(set(upward)))


def test_no_import_cycles():
    graph = _graph()
    state, cycles = {}, []

    def visit(node, stack):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                cycles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = "done"

    for node in sorted(graph):
        if node not in state and node != "cpas_bayes":  # the top-level API imports lazily, by name
            visit(node, [])
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_matplotlib_only_in_outputs_and_app():
    offenders = []
    for name, path in MODULES.items():
        if _layer(name) in MATPLOTLIB_LAYERS:
            continue
        for target, line in _imports(path):
            if target.split(".")[0] == "matplotlib":
                offenders.append(f"{path.relative_to(PACKAGE.parent)}:{line} imports {target}")
    assert not offenders, "matplotlib below the output layer:\n" + "\n".join(offenders)


def test_only_the_cli_selects_a_backend():
    selecting = [str(p.relative_to(PACKAGE.parent)) for name, p in MODULES.items()
                 if "matplotlib.use(" in p.read_text() and name != "cpas_bayes.app.cli_runtime"]
    assert not selecting, f"modules that switch the user's matplotlib backend: {selecting}"


def test_no_private_names_imported_across_modules():
    crossing = []
    for name, path in MODULES.items():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("cpas_bayes"):
                for alias in node.names:
                    if alias.name.startswith("_") and not alias.name.startswith("__"):
                        crossing.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} imports "
                                        f"{node.module}.{alias.name}")
    assert not crossing, "private names imported across modules:\n" + "\n".join(crossing)


@pytest.mark.parametrize("name", sorted(MODULES))
def test_module_size(name):
    lines = len(MODULES[name].read_text().splitlines())
    if name in ONE_CONCEPT:
        return
    assert lines <= MAX_LINES, f"{name} has {lines} lines (> {MAX_LINES}); split it along its sections"
