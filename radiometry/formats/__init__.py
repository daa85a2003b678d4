"""Foreign calibration formats, and loaders that pick the format from the file name.

- radical (C++ toolbox of Alexandrov et al.): ``.crf`` response, ``.vgn`` vignetting (LUT and polynomial).
- TUM / DSO photometric calibration: ``pcalib.txt`` (inverse response), 16-bit ``vignette.png``.
- radiomap's own ``.npz`` model files (:mod:`radiometry.fileio`).
"""

from __future__ import annotations

import os
from pathlib import Path


def load_response(path: str | os.PathLike):
    """Read a response from radiomap ``.npz``, radical ``.crf`` or DSO ``pcalib.txt`` (by suffix)."""
    from radiometry.response import CameraResponse

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".crf":
        from radiometry.formats.crf import read_radical_crf

        return read_radical_crf(path)
    if suffix == ".txt":
        from radiometry.formats.pcalib import read_pcalib

        return read_pcalib(path)
    return CameraResponse.load(path)


def load_vignetting(path: str | os.PathLike):
    """Read a vignetting model from radiomap ``.npz``, radical ``.vgn`` or DSO ``vignette.png``."""
    from radiometry.vignetting import VignettingModel

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".vgn":
        from radiometry.formats.vgn import read_radical_vgn

        return read_radical_vgn(path)
    if suffix == ".png":
        from radiometry.formats.dso_vignette import read_dso_vignette

        return read_dso_vignette(path)
    return VignettingModel.load(path)
