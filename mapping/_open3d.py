"""Import Open3D safely.

Two wheels install the same ``open3d`` package: ``open3d-cpu`` (the dependency on Linux x86-64, 312 MB) and
``open3d`` (there the CUDA build, 907 MB; elsewhere it is the CPU build). Only one may be installed: they
share their files, so installing one over the other mixes them and uninstalling either removes the files of
both. :func:`open3d_wheels` tells which is installed; a mix is logged as a warning with the fix.

Both Linux wheels link against ``libusb-1.0.so.0``, which a fresh machine lacks. The dependency
``libusb-package`` ships that library; loading it with ``RTLD_GLOBAL`` before importing open3d lets the
dynamic loader resolve it. Use ``from mapping._open3d import o3d`` everywhere instead of ``import open3d``.
"""

from __future__ import annotations

import logging
import os
import platform
import re
import sys
from pathlib import Path

from mapping._libusb import preload_libusb as _preload_libusb  # the one loader (import mapping runs it too)
from radiometry.errors import RadiomapError

log = logging.getLogger(__name__)

WHEELS = ("open3d-cpu", "open3d")
_DIST_INFO = re.compile(r"(open3d(?:[-_.]cpu)?)-[^-]+\.dist-info", re.IGNORECASE)
if sys.platform == "linux" and platform.machine() == "x86_64":  # the wheel pyproject.toml asks for here
    SWITCH = ("'pip uninstall -y open3d open3d-cpu', then 'pip install open3d-cpu' (or 'pip install open3d' for "
              "Open3D's CUDA build)")
else:
    SWITCH = "'pip uninstall -y open3d open3d-cpu', then 'pip install open3d'"


def open3d_wheels(site: str | os.PathLike | None = None) -> list[str]:
    """The Open3D wheels installed in ``site`` (default: where ``open3d`` was imported from), in the order
    of :data:`WHEELS`: ``["open3d-cpu"]`` or ``["open3d"]``; both is a mix, none an install without
    metadata. A directory listing, not ``importlib.metadata`` (which would add ~60 ms to every import)."""
    if site is None:
        import open3d

        site = Path(open3d.__file__).parent.parent
    try:
        names = os.listdir(site)
    except OSError:
        return []
    stems = {m.group(1).lower() for m in map(_DIST_INFO.fullmatch, names) if m}
    found = {"open3d" if stem == "open3d" else "open3d-cpu" for stem in stems}
    return [w for w in WHEELS if w in found]


def _wheels_missing_files() -> list[str]:
    """The Open3D wheels pip has metadata for (the first on ``sys.path``) whose ``open3d`` files are gone,
    as after uninstalling the other wheel. For the error message only: it reads the wheels' file lists."""
    from importlib import metadata

    broken = []
    for wheel in WHEELS:
        try:
            dist = metadata.distribution(wheel)
        except metadata.PackageNotFoundError:
            continue
        if any(f.parts[0] == "open3d" and not Path(dist.locate_file(f)).exists() for f in dist.files or ()):
            broken.append(wheel)
    return broken


def _cannot_import(reason: str) -> RadiomapError:
    broken = _wheels_missing_files()
    if broken:
        return RadiomapError(
            f"cannot import open3d ({reason}): files of {' and '.join(broken)} are missing (the two Open3D wheels "
            f"share them, and uninstalling one removes them); reinstall one: {SWITCH}")
    return RadiomapError(
        f"cannot import open3d ({reason}); reinstall with 'pip install radiomap' (it brings libusb-package), "
        "or install the system library with 'apt-get install libusb-1.0-0'")


def load_open3d():
    log.debug("libusb-1.0 loaded from %s", _preload_libusb())
    try:
        import open3d
    except ImportError as exc:
        raise _cannot_import(str(exc)) from None
    if getattr(open3d, "__file__", None) is None:   # a namespace package: what uninstalling a wheel leaves
        del sys.modules["open3d"]
        raise _cannot_import(f"only folders without Open3D in {', '.join(open3d.__path__)}")
    site = Path(open3d.__file__).parent.parent
    wheels = open3d_wheels(site)
    if len(wheels) > 1:
        log.warning("both Open3D wheels, %s, are installed in %s; they share the open3d files, so the build in "
                    "use (%s) is whichever was installed last and uninstalling either breaks both; keep one: %s",
                    " and ".join(wheels), site, build(open3d), SWITCH)
    return open3d


def build(module=None) -> str:
    """``"CUDA"`` if the loaded Open3D was built with CUDA (the ``open3d`` wheel on Linux x86-64), else
    ``"CPU"``."""
    config = getattr(module if module is not None else o3d, "_build_config", {})
    return "CUDA" if config.get("BUILD_CUDA_MODULE") else "CPU"


_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_TAG = re.compile(r"\[Open3D (?:Error|Warning)\]\s*")
_SOURCE = re.compile(r"\S+\.(?:cpp|cc|h|cu|cuh):\d+:\s*")   # '/root/Open3D/cpp/.../File.cpp:220: '


def open3d_message(exc: BaseException) -> str:
    """Open3D's error text without terminal colour codes, the C++ signature and the source location:
    ``'Singular 6x6 linear system detected, tracking failed.'``."""
    text = " ".join(_ANSI.sub("", str(exc)).split())
    source = list(_SOURCE.finditer(text))
    short = text[source[-1].end():] if source else _TAG.sub("", text)
    return short.strip() or text


o3d = load_open3d()
