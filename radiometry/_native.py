"""Which implementation runs radiomap's per-pixel kernels: compiled C or Numba.

Every kernel of the TSDF path, the display look-ups, the depth pyramid and the uint8 correction has two
implementations with the same arguments and the same results (``tests/test_native_kernels.py``): a C extension
built at install (``setup.py``; ``mapping._ckernels``, ``radiometry._ckernels``) and a Numba kernel compiled at
first use. C is the default: Numba's runtime costs ~111 MB in every process that calls a kernel (LLVM is
loaded even to run kernels from its on-disk cache), more than radiomap's memory budget against Open3D's own
SLAM loop (README "Benchmarks"). Numba runs them where the extensions were not built (no C compiler at install)
or when asked. The surfel backend and the vignetting accumulator have Numba kernels only.

``RADIOMAP_KERNELS``: ``auto`` (default: C when built, else Numba), ``c`` (fail when not built) or ``numba``.
"""

from __future__ import annotations

import importlib
import logging
import os
from types import ModuleType

log = logging.getLogger(__name__)

CHOICES = ("auto", "c", "numba")


def choice() -> str:
    """The value of ``RADIOMAP_KERNELS`` (``auto`` when unset)."""
    value = os.environ.get("RADIOMAP_KERNELS", "").strip().lower() or "auto"
    if value not in CHOICES:
        raise ValueError(f"RADIOMAP_KERNELS={value!r} is not a kernel choice: set it to auto, c or numba "
                         f"(or unset it)")
    return value


def compiled(module: str) -> ModuleType | None:
    """The C extension ``module`` (e.g. ``"mapping._ckernels"``), or None when the Numba kernels are to run:
    ``RADIOMAP_KERNELS=numba``, or ``auto`` and the extension was not built. ``c`` and not built: ImportError."""
    wanted = choice()
    if wanted == "numba":
        return None
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        if wanted == "c":
            raise ImportError(f"RADIOMAP_KERNELS=c but {module} is not built ({exc}): reinstall radiomap where a C "
                              f"compiler is found (pip install -e .), or unset RADIOMAP_KERNELS to use Numba's "
                              f"kernels") from exc
        log.info("%s is not built (%s): radiomap runs its Numba kernels (~110 MB more memory)", module, exc)
        return None
