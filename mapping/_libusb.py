"""Make ``libusb-1.0.so.0`` loadable for the open3d wheel without importing open3d.

The open3d wheel links against ``libusb-1.0.so.0``, which a fresh machine lacks; the dependency
``libusb-package`` ships that library. Loading it with ``RTLD_GLOBAL`` lets the dynamic loader resolve
open3d's dependency later. ``import mapping`` does it (a few milliseconds: no open3d, no libusb_package
import), so a notebook that runs ``import mapping`` before ``import open3d`` works; and an ``import open3d``
that already failed works when retried after ``import mapping``.
"""

from __future__ import annotations

import ctypes
import importlib.util
import logging
from pathlib import Path

log = logging.getLogger(__name__)

SONAME = "libusb-1.0.so.0"


def _packaged_library() -> Path | None:
    """libusb-package's copy of the library, found without importing the package (that costs ~70 ms)."""
    try:
        spec = importlib.util.find_spec("libusb_package")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for folder in spec.submodule_search_locations:
        found = sorted(Path(folder).glob("libusb-1.0*.so*"))
        if found:
            return found[0]
    return None


def preload_libusb() -> str | None:
    """Load libusb globally: the system's if there is one, else libusb-package's. Returns what was loaded
    (``SONAME`` or the packaged file), or None when neither loads (open3d's import will then say so)."""
    try:
        ctypes.CDLL(SONAME, mode=ctypes.RTLD_GLOBAL)
        return SONAME
    except OSError:
        pass
    path = _packaged_library()
    if path is None:
        try:
            import libusb_package

            path = libusb_package.get_library_path()
        except Exception:  # pragma: no cover - depends on the machine
            path = None
    if path is None:
        return None
    try:
        ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    except OSError as exc:  # pragma: no cover
        log.debug("could not load %s: %s", path, exc)
        return None
    return str(path)
