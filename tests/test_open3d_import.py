"""A failing ``import open3d`` becomes one RadiomapError line naming the fix (``mapping/_open3d.py``).

Run in a subprocess, so that this process's real open3d import state is untouched.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

PROBE = """
import json, sys
{block}
from radiometry.errors import RadiomapError
try:
    import mapping._open3d
except RadiomapError as exc:
    print(json.dumps({{"type": type(exc).__name__, "message": str(exc), "loaded": "mapping._open3d" in sys.modules}}))
else:
    print(json.dumps({{"type": None, "message": "", "loaded": True}}))
"""


def run_probe(block: str, tmp_path: Path, extra_path: Path | None = None) -> dict:
    env = dict(os.environ)
    if extra_path is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(extra_path), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    proc = subprocess.run([sys.executable, "-c", PROBE.format(block=block)], capture_output=True, text=True,
                          cwd=tmp_path, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


FIX = ("reinstall with 'pip install radiomap' (it brings libusb-package), or install the system library with "
       "'apt-get install libusb-1.0-0'")


def test_open3d_blocked_in_sys_modules(tmp_path):
    result = run_probe("sys.modules['open3d'] = None", tmp_path)
    assert result["type"] == "RadiomapError" and not result["loaded"]
    message = result["message"]
    assert "\n" not in message
    assert message.startswith("cannot import open3d (import of open3d halted; None in sys.modules); ")
    assert message.endswith(FIX)


def test_open3d_missing_its_shared_library(tmp_path):
    """What a fresh machine without libusb sees: the wheel's extension fails to load."""
    fake = tmp_path / "site"
    (fake / "open3d").mkdir(parents=True)
    (fake / "open3d" / "__init__.py").write_text(
        'raise ImportError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")\n')
    result = run_probe("", tmp_path, extra_path=fake)
    assert result["type"] == "RadiomapError"
    assert result["message"] == ("cannot import open3d (libusb-1.0.so.0: cannot open shared object file: No such file "
                                 f"or directory); {FIX}")


def test_a_working_open3d_imports(tmp_path):
    """The probe itself can tell success from failure."""
    if importlib.util.find_spec("open3d") is None:  # not imported here: that needs libusb preloaded
        pytest.skip("open3d is not installed")
    result = run_probe("", tmp_path)
    assert result["type"] is None and result["loaded"]
