"""mapping: RGB-D datasets, ICP tracking, TSDF and surfel fusion of irradiance, colour-coherence metrics.

From Python: ``mapping.reconstruct_sequence(path, output=None, *, response=..., vignetting=...)`` (see
:mod:`mapping.api`). Importing ``mapping`` is light (no Open3D); it makes the libusb that the open3d wheel
needs loadable (:mod:`mapping._libusb`), so ``import mapping`` before ``import open3d`` works on a machine
without the system library.
"""

from mapping._libusb import preload_libusb as _preload_libusb

_preload_libusb()

#: re-exported names, imported when first used: ``import mapping`` stays light (no NumPy), so that the command's entry
#: point (:mod:`mapping._entry`) can catch a Ctrl-C during the heavy imports and end with one line
_LAZY = {"Reconstruction": "mapping.api", "reconstruct_sequence": "mapping.api", "__version__": "radiometry"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'mapping' has no attribute {name!r}")


__all__ = ["Reconstruction", "reconstruct_sequence"]
