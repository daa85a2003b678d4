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
