"""mapping: RGB-D datasets, ICP tracking, TSDF and surfel fusion of irradiance, colour-coherence metrics.

From Python: ``mapping.reconstruct_sequence(path, output=None, *, response=..., vignetting=...)`` (see
:mod:`mapping.api`). Importing ``mapping`` is light (no Open3D); it makes the libusb that the open3d wheel
needs loadable (:mod:`mapping._libusb`), so ``import mapping`` before ``import open3d`` works on a machine
without the system library.
"""

from radiometry import __version__  # noqa: F401  (one version for the distribution)

from mapping._libusb import preload_libusb as _preload_libusb
from mapping.api import Reconstruction, reconstruct_sequence  # noqa: F401  (re-exported)

_preload_libusb()

__all__ = ["Reconstruction", "reconstruct_sequence"]
