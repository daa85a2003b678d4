"""The shape of the code (docs/architecture.md): one module list that stays current, files of one job, one
direction of imports (the CLI only at the top, ``radiometry`` never importing ``mapping``)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("radiometry", "mapping")
MAX_LINES = 700


def _sources(*folders: str) -> list[Path]:
    return sorted(p for f in folders for p in (ROOT / f).rglob("*.py") if "__pycache__" not in p.parts)


def _imported_modules(path: Path) -> set[str]:
    """Every module an ``import`` or ``from ... import`` statement names (at any depth, also inside functions)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return names


def test_every_module_is_listed_in_the_architecture_document():
    listed = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    missing = [str(p.relative_to(ROOT)) for p in _sources(*PACKAGES) if f"`{p.relative_to(ROOT).as_posix()}`" not in listed]
    assert not missing, f"docs/architecture.md has no line for {missing}; add one (what the module is for)"


def test_listed_modules_exist():
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    module_list = text.split("## One line per module", 1)[1]
    named = [line.split("`")[1] for line in module_list.splitlines() if line.startswith("- `")]
    assert named, "the module list of docs/architecture.md is empty"
    assert [n for n in named if not (ROOT / n).exists()] == []


@pytest.mark.parametrize("folder", [*PACKAGES, "scripts", "tests"])
def test_no_source_file_is_over_700_lines(folder):
    long = {str(p.relative_to(ROOT)): n for p in _sources(folder)
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_LINES}
    assert not long, f"split these into files of one job each: {long}"


def test_only_the_cli_imports_the_cli():
    offenders = [str(p.relative_to(ROOT)) for p in _sources(*PACKAGES, "scripts", "docs")
                 if "cli" not in p.relative_to(ROOT).parts[1:2]
                 and p.relative_to(ROOT).as_posix() != "mapping/_entry.py"   # the command's entry point: it starts it
                 and any(m == "mapping.cli" or m.startswith("mapping.cli.") for m in _imported_modules(p))]
    assert not offenders, f"the CLI parses options and calls the library; move what these need into it: {offenders}"


def test_radiometry_does_not_import_mapping():
    offenders = [str(p.relative_to(ROOT)) for p in _sources("radiometry")
                 if any(m == "mapping" or m.startswith("mapping.") for m in _imported_modules(p))]
    assert not offenders, f"radiometry must stand alone (mapping builds on it): {offenders}"


def _module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the radiometry/mapping modules it imports, from every ``import`` statement: at the top of the file
    and inside functions alike (a function-level import is a cycle that only waits for its call). ``from pkg import
    sub`` counts as importing the module ``pkg.sub``; ``from pkg import name`` as importing ``pkg``. The parent
    packages Python imports on the way are not counted (they are not a choice of the importing module), nor are
    imports by a string (``Registry`` entries, ``importlib``)."""
    files = {_module_name(p, root): p for f in PACKAGES for p in (root / f).rglob("*.py") if "__pycache__" not in p.parts}
    graph = {}
    for name, path in files.items():
        edges = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                edges.update(a.name for a in node.names if a.name in files)
            elif isinstance(node, ast.ImportFrom) and node.module:
                base = node.module
                if node.level:  # relative: resolve against this module's package
                    pkg = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                    base = ".".join(pkg[:len(pkg) - node.level + 1] + [node.module])
                for a in node.names:
                    edges.add(f"{base}.{a.name}" if f"{base}.{a.name}" in files else base)
        graph[name] = {e for e in edges if e in files and e != name}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative), each sorted."""
    index, low, on_stack, stack, cycles = {}, {}, set(), [], []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[v] = min(low[v], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))
    return cycles


def test_import_cycle_finder_finds_a_cycle_of_function_level_imports():
    # the shape of the old radiometry.response_fit <-> response_lambda cycle: one side imports inside a function
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert import_cycles(graph) == [["a", "b", "c"]]
    assert import_cycles({"a": {"b"}, "b": set()}) == []
    real = import_graph()
    assert "radiometry.response.model" in real["radiometry.response.fit"]      # a top-level import
    assert "radiometry.response.fit" in real["radiometry.response.quality"]    # an import inside a function


def test_no_import_cycles_among_radiometry_and_mapping_modules():
    cycles = import_cycles(import_graph())
    assert not cycles, ("these modules import each other (at the top or inside functions); move what they share "
                        f"into a small module below both: {cycles}")
