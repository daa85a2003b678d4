"""Import Open3D safely.

The open3d wheel links against ``libusb-1.0.so.0``, which a fresh machine lacks. The dependency
``libusb-package`` ships that library; loading it with ``RTLD_GLOBAL`` before importing open3d lets
the dynamic loader resolve it. Use ``from mapping._open3d import o3d`` everywhere instead of
``import open3d``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import re

from radiometry.errors import RadiomapError

log = logging.getLogger(__name__)


def _preload_libusb() -> None:
    try:
        ctypes.CDLL("libusb-1.0.so.0", mode=ctypes.RTLD_GLOBAL)
        return
    except OSError:
        pass
    try:
        import libusb_package

        path = libusb_package.get_library_path()
    except Exception:  # pragma: no cover - depends on the machine
        path = None
    if path is not None:
        try:
            ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        except OSError as exc:  # pragma: no cover
            log.debug("could not load %s: %s", path, exc)


def load_open3d():
    _preload_libusb()
    try:
        import open3d
    except ImportError as exc:
        raise RadiomapError(
            f"cannot import open3d ({exc}); reinstall with 'pip install radiomap' (it brings libusb-package), "
            "or install the system library with 'apt-get install libusb-1.0-0'") from None
    return open3d


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
