"""Run the fast test tier (`pytest -m "not slow"`), time it, and check that it imports every source module.

    python scripts/fast_tier.py                 # the tier, its wall and CPU time, the load, and the module census
    python scripts/fast_tier.py -- -x -q        # extra pytest arguments after --

The census: every module under radiometry/ and mapping/ must be imported by the pytest process of the fast tier
(a module that only a child process imports, e.g. through `python -m mapping ...`, does not count). The script
prints the modules no fast test imports and exits 1 when there are any, or when a test failed. It is also a pytest
plugin (`-p fast_tier`, with scripts/ on the path) that writes the imported modules to $FAST_TIER_MODULES.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("radiometry", "mapping")
#: modules a fast test runs only in a child process (which the census cannot see), and the test
IN_A_CHILD = {"mapping._entry": "tests/test_robustness_inputs31.py::test_ctrl_c_while_the_command_is_still_importing_is_one_line"}


def pytest_sessionfinish(session, exitstatus):  # the plugin half: runs inside pytest
    target = os.environ.get("FAST_TIER_MODULES")
    if target:
        names = sorted(m for m in sys.modules if m.split(".")[0] in PACKAGES)
        Path(target).write_text("\n".join(names) + "\n", encoding="utf-8")


def source_modules() -> list[str]:
    """Dotted names of every source module (packages by their __init__)."""
    names = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__main__":
                continue
            if parts[-1] == "__init__":
                parts = parts[:-1]
            names.append(".".join(parts))
    return names


def main(argv: list[str]) -> int:
    extra = argv[argv.index("--") + 1:] if "--" in argv else ["-q"]
    with tempfile.TemporaryDirectory() as tmp:
        census = Path(tmp) / "modules.txt"
        env = dict(os.environ, FAST_TIER_MODULES=str(census),
                   PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT / "scripts"), os.environ.get("PYTHONPATH")])))
        load0 = os.getloadavg()[0]
        start = time.monotonic()
        proc = subprocess.run([sys.executable, "-m", "pytest", "-m", "not slow", "-p", "fast_tier", *extra],
                              cwd=ROOT, env=env)
        wall = time.monotonic() - start
        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        imported = set(census.read_text(encoding="utf-8").split()) if census.exists() else set()
    missing = [name for name in source_modules() if name not in imported and name not in IN_A_CHILD]
    print(f"fast tier: exit {proc.returncode}, {wall:.0f} s wall, {usage.ru_utime + usage.ru_stime:.0f} s CPU, "
          f"on {os.cpu_count()} cores, load average {load0:.1f} at the start and {os.getloadavg()[0]:.1f} at the end")
    print(f"modules imported by the fast tier: {len(source_modules()) - len(missing)} of {len(source_modules())}")
    for name, test in IN_A_CHILD.items():
        print(f"  run in a child process by a fast test: {name} ({test})")
    for name in missing:
        print(f"  not imported by any fast test: {name}")
    return 1 if (missing or proc.returncode) else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
