"""Which implementation runs radiomap's per-pixel kernels: compiled C or Numba.

Every kernel of the TSDF path, the display look-ups, the depth pyramid and the uint8 correction has two
implementations with the same arguments and the same results (``tests/test_native_kernels.py``): a C extension
built at install (``setup.py``; ``mapping._ckernels``, ``radiometry._ckernels``) and a Numba kernel compiled at
first use. C is the default: Numba's runtime costs ~111 MB in every process that calls a kernel (LLVM is
loaded even to run kernels from its on-disk cache), more than radiomap's memory budget against Open3D's own
SLAM loop (docs/benchmarks.md). Numba runs them where the extensions were not built (no C compiler at install),
cannot be loaded, were built for another version of the kernels (:data:`ABI`), or when asked. The surfel backend
and the vignetting accumulator have Numba kernels only.

``RADIOMAP_KERNELS``: ``auto`` (default: C when usable, else Numba), ``c`` (fail when not usable) or ``numba``.
"""

from __future__ import annotations

import importlib
import logging
import os
from types import ModuleType

from radiometry.errors import InstallationError

log = logging.getLogger(__name__)

CHOICES = ("auto", "c", "numba")
_SIMD_OFF = ("0", "off", "no", "false", "scalar")

#: the kernels' argument contract; each C module exports the number it was built with (``ABI``). Bump it here and
#: in ``radiometry/_buffers.h`` whenever a kernel's arguments change: a stale build is then not used.
ABI = 3

_LOADED: dict[str, tuple[ModuleType | None, str]] = {}


def choice() -> str:
    """The value of ``RADIOMAP_KERNELS`` (``auto`` when unset)."""
    value = os.environ.get("RADIOMAP_KERNELS", "").strip().lower() or "auto"
    if value not in CHOICES:
        raise InstallationError(f"RADIOMAP_KERNELS={value!r} is not a kernel choice: set it to auto, c or numba "
                                f"(or unset it)")
    return value


def simd_allowed() -> bool:
    """Whether the C kernels may use their AVX-512 paths where the CPU has them (the uint8 correction, the ray
    cast's march; both give the scalar kernels' bits): not when ``RADIOMAP_SIMD`` is ``0``/``off``/``scalar``."""
    value = os.environ.get("RADIOMAP_SIMD")
    return not value or value.strip().lower() not in _SIMD_OFF


def _load(module: str) -> tuple[ModuleType | None, str]:
    """The extension and '' when it is usable, else None and why not."""
    try:
        mod = importlib.import_module(module)
    except Exception as exc:  # noqa: BLE001 - not built (ImportError), or a broken file (any error at load)
        return None, f"{module} cannot be loaded ({type(exc).__name__}: {exc})"
    built = getattr(mod, "ABI", None)
    if built != ABI:
        return None, f"{module} was built for other kernels (ABI {built}, this radiomap needs {ABI})"
    return mod, ""


def unusable(module: str) -> str:
    """Why the C extension ``module`` cannot be used ('' when it can), whatever ``RADIOMAP_KERNELS`` says."""
    if module not in _LOADED:
        _LOADED[module] = _load(module)
    return _LOADED[module][1]


def compiled(module: str) -> ModuleType | None:
    """The C extension ``module`` (e.g. ``"mapping._ckernels"``), or None when the Numba kernels are to run:
    ``RADIOMAP_KERNELS=numba``, or ``auto`` and the extension is not usable (said once, at INFO). ``c`` and not
    usable: :class:`~radiometry.errors.InstallationError`."""
    wanted = choice()
    if wanted == "numba":
        return None
    first = module not in _LOADED
    why = unusable(module)
    if not why:
        return _LOADED[module][0]
    if wanted == "c":
        raise InstallationError(f"RADIOMAP_KERNELS=c but {why}: reinstall radiomap where a C compiler is found "
                                f"(pip install -e .), or unset RADIOMAP_KERNELS to use Numba's kernels")
    if first:
        log.info("%s: radiomap runs its Numba kernels (~110 MB more memory); pip install -e . with a C compiler "
                 "builds them", why)
    return None
