"""A failing ``import open3d`` becomes one RadiomapError line naming the fix; one Open3D wheel is installed
and libusb is preloaded for it (``mapping/_open3d.py``).

Imports are probed in a subprocess, so that this process's real open3d import state is untouched.
"""

from __future__ import annotations

import importlib.util
import json
import os
import platform
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
    return {**json.loads(proc.stdout.strip().splitlines()[-1]), "stderr": proc.stderr}


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


def fake_site(tmp_path: Path, dist_infos: dict[str, str], cuda: bool | None = None) -> Path:
    """A site directory with these ``*.dist-info`` folders (name: RECORD text) and, unless ``cuda`` is None, a
    stand-in ``open3d`` package of that build."""
    site = tmp_path / "site"
    site.mkdir()
    for name, record in dist_infos.items():
        (site / name).mkdir()
        wheel = name.split("-")[0].replace("_", "-")
        (site / name / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {wheel}\nVersion: 0.20.0\n")
        (site / name / "RECORD").write_text(record)
    if cuda is not None:
        (site / "open3d").mkdir()
        (site / "open3d" / "__init__.py").write_text(f"_build_config = {{'BUILD_CUDA_MODULE': {cuda}}}\n")
    return site


def test_one_open3d_wheel_and_the_build_it_names():
    from mapping._open3d import build, open3d_wheels

    wheels = open3d_wheels()
    if not wheels:
        pytest.skip("open3d is installed without pip metadata (a source build?)")
    assert len(wheels) == 1, f"{wheels} are installed together: they share the open3d files"
    if wheels == ["open3d-cpu"]:
        assert build() == "CPU"
    elif sys.platform == "linux" and platform.machine() == "x86_64":
        assert build() == "CUDA"   # what the open3d wheel is here, and why pyproject asks for open3d-cpu


def test_both_wheels_installed_warns_with_the_fix(tmp_path):
    from mapping._open3d import SWITCH

    site = fake_site(tmp_path, {"open3d-0.20.0.dist-info": "", "open3d_cpu-0.20.0.dist-info": ""}, cuda=False)
    result = run_probe("", tmp_path, extra_path=site)
    assert result["type"] is None and result["loaded"]
    assert (f"both Open3D wheels, open3d-cpu and open3d, are installed in {site}; they share the open3d files, so "
            f"the build in use (CPU) is whichever was installed last and uninstalling either breaks both; keep one: "
            f"{SWITCH}") in result["stderr"]


def test_a_wheel_whose_files_the_other_removed(tmp_path):
    """``pip uninstall open3d`` after both were installed leaves open3d-cpu's metadata without its files."""
    from mapping._open3d import SWITCH

    site = fake_site(tmp_path, {"open3d_cpu-0.20.0.dist-info": "open3d/__init__.py,,\nopen3d/pybind.so,,\n"})
    result = run_probe("sys.modules['open3d'] = None", tmp_path, extra_path=site)
    assert result["type"] == "RadiomapError"
    assert result["message"] == ("cannot import open3d (import of open3d halted; None in sys.modules): files of "
                                 "open3d-cpu are missing (the two Open3D wheels share them, and uninstalling one "
                                 f"removes them); reinstall one: {SWITCH}")


def test_the_folders_an_uninstall_leaves_behind(tmp_path):
    """What pip leaves of the shared files (folders it did not create, such as ``open3d/labextension``) imports
    as an empty namespace package; that is no Open3D."""
    from mapping._open3d import SWITCH

    site = fake_site(tmp_path, {"open3d_cpu-0.20.0.dist-info": "open3d/__init__.py,,\n"})
    (site / "open3d" / "labextension").mkdir(parents=True)
    # the fake site instead of site-packages for open3d and its metadata (mapping, numpy, libusb_package loaded)
    block = f"import mapping, radiometry, libusb_package; sys.path[:] = [{str(site)!r}] + [p for p in sys.path if " \
            "not p.endswith(('site-packages', 'dist-packages'))]"
    result = run_probe(block, tmp_path)
    assert result["type"] == "RadiomapError" and not result["loaded"]
    assert result["message"] == (f"cannot import open3d (only folders without Open3D in {site / 'open3d'}): files "
                                 "of open3d-cpu are missing (the two Open3D wheels share them, and uninstalling one "
                                 f"removes them); reinstall one: {SWITCH}")


LIBUSB_MAPS = """
import json, sys
{block}
maps = open("/proc/self/maps").read().splitlines()
print(json.dumps(sorted({{line.split()[-1] for line in maps if "libusb-1.0" in line}})))
"""


@pytest.mark.skipif(sys.platform != "linux", reason="the wheels link libusb-1.0.so.0 on Linux")
def test_libusb_preloaded_where_the_system_has_none(tmp_path):
    if importlib.util.find_spec("open3d") is None:
        pytest.skip("open3d is not installed")
    plain = subprocess.run([sys.executable, "-c", "import open3d"], capture_output=True, text=True, cwd=tmp_path,
                           timeout=300)
    ours = subprocess.run([sys.executable, "-c", LIBUSB_MAPS.format(block="import mapping._open3d")],
                          capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert ours.returncode == 0, ours.stderr
    mapped = json.loads(ours.stdout.strip().splitlines()[-1])
    if plain.returncode == 0:   # the system has libusb (or a later wheel no longer links it)
        return
    assert "libusb-1.0.so.0: cannot open shared object file" in plain.stderr
    import libusb_package

    assert mapped == [str(Path(libusb_package.get_library_path()).resolve())]
