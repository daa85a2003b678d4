"""The documentation cannot silently break: the mkdocs site builds with --strict (every link and anchor resolves,
every page is in the nav), the command reference matches the commands' --help, every studies page names the command
that reproduces it and its date, the README stays short with working links, and the README's tour runs as written
(at a smaller size)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")


def _nav_pages(section: str) -> list[str]:
    """The pages listed under a top-level section of mkdocs.yml's nav."""
    import yaml

    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))
    for entry in config["nav"]:
        if isinstance(entry, dict) and section in entry:
            return [page for item in entry[section] for page in item.values()]
    raise AssertionError(f"mkdocs.yml has no nav section {section!r}")


def test_mkdocs_builds_with_strict(tmp_path):
    """`mkdocs build --strict`: a broken link or anchor, or a page missing from the nav, fails the build."""
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-f", str(ROOT / "mkdocs.yml"),
                           "-d", str(tmp_path / "site")], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert "No module named mkdocs" not in proc.stderr, "mkdocs is missing: pip install -e '.[test]'"
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for page in ("index.html", "guides/calibrate/index.html", "reference/commands/index.html",
                 "robustness_catalogue/index.html"):
        assert (tmp_path / "site" / page).is_file(), page


def test_command_reference_matches_the_help():
    """docs/reference/commands.md is what `python -m mapping.cli._reference` generates from every --help."""
    from mapping.cli import SUBCOMMANDS, _reference

    assert _reference.main(["--check"]) == 0, "run: python -m mapping.cli._reference"

    page = (ROOT / "docs" / "reference" / "commands.md").read_text(encoding="utf-8")
    for name in SUBCOMMANDS:
        assert f"## radiomap {name}\n" in page, name


@pytest.mark.parametrize("section", ["Studies and benchmarks", "Robustness"])
def test_studies_name_their_command_and_date(section):
    """Numbers in the docs come from scripts: each studies page says which command reproduces it, and when."""
    pages = _nav_pages(section)
    assert pages
    for page in pages:
        text = (ROOT / "docs" / page).read_text(encoding="utf-8")
        head = text.split("\n## ", 1)[0]
        line = re.search(r"\*\*Reproduce:\*\*(.*?)(\n\n|$)", head, re.S)
        assert line, f"docs/{page}: no '**Reproduce:**' line before its first section"
        assert "`" in line.group(1), f"docs/{page}: the Reproduce line names no command"
        assert DATE.search(line.group(1)), f"docs/{page}: the Reproduce line gives no date (YYYY-MM-DD)"


def test_readme_is_short_and_its_links_resolve():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 300, "README.md is over 300 lines: put the rest in docs/"
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [link for link in links if not re.match(r"[a-z]+://", link)]
    assert len(local) > 10
    missing = [link for link in local if not (ROOT / link).exists()]
    assert not missing, f"README.md links to missing files: {missing}"
    assert not re.search(r"\b(CMD_TIMES|TOUR_\w+|FAST_TIER)\b", text), "README.md has a placeholder left"


def _tour_script() -> str:
    """The README's tour block, as written (its sizes are small already)."""
    text = README.read_text(encoding="utf-8")
    assert "<!-- tour:" in text, "README.md lost the tour marker (tests/test_docs.py runs the block after it)"
    block = re.search(r"<!-- tour:.*?-->\n```bash\n(.*?)\n```\n", text, re.S)
    assert block, "no bash block after the tour marker"
    script = block.group(1)
    assert script.startswith("source .venv/bin/activate\n")
    return "set -euo pipefail\n" + script.split("\n", 1)[1]


def _numbers(line: str) -> list[float]:
    return [float(v) for v in re.findall(r"\d+\.\d+|\d+", line.split(":", 1)[1])]


@pytest.mark.slow
def test_readme_tour_runs_and_prints_what_the_readme_says(tmp_path):
    """Every command of the README's tour exits 0 and writes what its comment says; step 6 prints the figures the
    README quotes (to 0.02: the fits are deterministic, the last digit may move with the BLAS threads), and step 5's
    L1 means are the README's."""
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    env.pop("PYTHONPATH", None)
    proc = subprocess.run(["bash", "-c", _tour_script()], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=1800)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for path in ("brackets/times.txt", "cal/crf.npz", "cal/crf.png", "cal/crf.json", "cal/vgn_lut.npz",
                 "cal/vgn_poly.npz", "runs/lut/metrics.json", "runs/lut/trajectory.txt", "runs/compare/report.html"):
        assert (tmp_path / path).is_file(), path
    assert len(list((tmp_path / "corrected").glob("*.png"))) == 60   # and correct's record, .radiomap-correct.json

    readme = README.read_text(encoding="utf-8")
    quoted = re.search(r"Step 6\s+prints:\n\n```text\n(.*?)```", readme, re.S)
    assert quoted, "README.md no longer quotes what step 6 prints"
    printed = {line.split(":", 1)[0]: line for line in proc.stdout.splitlines()
               if line.startswith(("response: max", "vignetting lut:", "vignetting poly:"))}
    for line in quoted.group(1).strip().splitlines():
        key = line.split(":", 1)[0]
        assert key in printed, (key, proc.stdout[-2000:])
        assert _numbers(printed[key]) == pytest.approx(_numbers(line), abs=0.02), (printed[key], line)

    ranks = re.search(r"by the mean colour disagreement L1 \(levels\): (.*?) \(", readme, re.S)
    assert ranks, "README.md no longer quotes step 5's L1 means"
    table = {row.split()[0]: row.split() for row in proc.stdout.splitlines()
             if row.split() and row.split()[0] in ("none", "poly", "lut", "poly+ec", "lut+ec")}
    for method, value in re.findall(r"([a-z+]+) (\d+\.\d+)", ranks.group(1).replace("\n", " ")):
        columns = table[method]
        l1_mean = float(columns[-6])   # ... pairs, L1 mean, L1 median, L1 p90, colour err, colour err p90, seconds
        assert l1_mean == pytest.approx(float(value), abs=0.05), (method, columns)
