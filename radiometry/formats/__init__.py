"""Foreign calibration formats, and loaders and writers that pick the format from the file name.

- radical (C++ toolbox of Alexandrov et al.): ``.crf`` response, ``.vgn`` vignetting (LUT and polynomial).
- TUM / DSO photometric calibration: ``pcalib.txt`` (inverse response), 16-bit ``vignette.png``.
- radiomap's own ``.npz`` model files (:mod:`radiometry.fileio`).

Each table maps a suffix to a ``"module:function"`` imported on first use.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from radiometry.errors import CalibrationFileError
from radiometry.registry import Registry

log = logging.getLogger(__name__)

#: response readers by suffix; any other suffix is read as radiomap's .npz (``CameraResponse.load``)
RESPONSE_READERS = Registry("response file suffix", {".crf": "radiometry.formats.crf:read_radical_crf",
                                                     ".txt": "radiometry.formats.pcalib:read_pcalib"})
#: vignetting readers by suffix; any other suffix is read as radiomap's .npz (``VignettingModel.load``)
VIGNETTING_READERS = Registry("vignetting file suffix", {
    ".vgn": "radiometry.formats.vgn:read_radical_vgn",
    ".png": "radiometry.formats.dso_vignette:read_dso_vignette"})


def _save_npz(model, path: str | os.PathLike) -> Path:
    """radiomap's own model file (the model's ``save``)."""
    return model.save(path)


#: vignetting writers ``(model, path)`` by suffix; the keys are the formats a calibration can be saved in
VIGNETTING_WRITERS = Registry("vignetting file suffix", {
    ".npz": _save_npz,
    ".vgn": "radiometry.formats.vgn:write_radical_vgn",
    ".png": "radiometry.formats.dso_vignette:write_dso_vignette"})


def read_file(path: Path, what: str) -> bytes:
    """The bytes of the model file ``path`` (``what`` names it in the errors: "the radical response"), or
    :class:`CalibrationFileError` when it is missing, a folder or unreadable."""
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such file; check the path of {what}")
    try:
        return path.read_bytes()
    except OSError as exc:
        raise CalibrationFileError(f"{path}: cannot read ({exc.strerror or exc}); check its permissions") from None


def _reader(path: Path, readers: Registry, own):
    """The reader of ``path``'s suffix, or ``own`` (radiomap's .npz reader) for any other suffix; a file of another
    suffix that is no radiomap model either is refused naming its suffix (:func:`_foreign`)."""
    suffix = path.suffix.lower()
    if suffix in readers:
        return readers[suffix]
    if suffix in (".npz", ".npy"):   # a bare .npy array: radiomap's reader says which command makes a model
        return own

    def read(p: Path):
        try:
            return own(p)
        except CalibrationFileError as exc:
            if not p.is_file():
                raise
            raise CalibrationFileError(_foreign(p, readers, exc)) from None
    return read


def _foreign(path: Path, readers: Registry, exc: Exception) -> str:
    """Why ``path`` (no .npz, none of ``readers``' suffixes) cannot be read: what it looks like, and what to pass."""
    response = readers is RESPONSE_READERS
    what, other = ("response", VIGNETTING_READERS) if response else ("vignetting model", RESPONSE_READERS)
    wanted = ("radiomap .npz, radical .crf or DSO pcalib.txt" if response else
              "radiomap .npz, radical .vgn or DSO vignette.png")
    suffix = path.suffix.lower()
    if suffix in other:
        return (f"{path}: a {'vignetting' if response else 'response'} file ({suffix}), not a {what}; pass the "
                f"{what}: {wanted}")
    if suffix == ".json":
        return (f"{path}: a JSON file (radiomap's record of a run, written beside its model), not a {what}; pass the "
                f"model file: {wanted}")
    return f"{path}: unknown {what} file extension {suffix or '(none)'!r} and not a radiomap .npz model; pass {wanted}"


def load_response(path: str | os.PathLike):
    """Read a response from radiomap ``.npz``, radical ``.crf`` or DSO ``pcalib.txt`` (by suffix). A response graded
    broken or doubtful when it was calibrated (``meta["quality"]["grade"]``, :mod:`radiometry.response.quality`) is
    logged as one warning naming the file (once per file and process)."""
    from radiometry.response import CameraResponse

    path = Path(path)
    response = _reader(path, RESPONSE_READERS, CameraResponse.load)(path)
    _warn_grade(path, response)
    return response


#: the response files whose grade has been warned about in this process (a command may load its response twice)
_WARNED: set[str] = set()


def _warn_grade(path: Path, response) -> None:
    quality = (getattr(response, "meta", None) or {}).get("quality")
    grade = quality.get("grade") if isinstance(quality, dict) else None
    key = os.path.realpath(path)
    if grade not in ("broken", "doubtful") or key in _WARNED:
        return
    _WARNED.add(key)
    start = str(quality.get("summary") or f"quality {grade}").split("; ")[0]
    log.warning("%s: this response was graded %s when it was calibrated (%s); what is computed through it is only "
                "as right as it is%s", path, "BROKEN" if grade == "broken" else grade, start,
                ": calibrate it again (radiomap response)" if grade == "broken" else
                ": its record (radiomap response's .json) says why")


def load_vignetting(path: str | os.PathLike):
    """Read a vignetting model from radiomap ``.npz``, radical ``.vgn`` or DSO ``vignette.png``."""
    from radiometry.vignetting import VignettingModel

    path = Path(path)
    return _reader(path, VIGNETTING_READERS, VignettingModel.load)(path)


def save_vignetting(model, path: str | os.PathLike) -> Path:
    """Write ``model`` in the format its suffix names: ``.npz`` (radiomap), ``.vgn`` (radical) or ``.png`` (DSO
    16-bit vignette, the channel mean); ValueError naming the three for any other suffix."""
    path = Path(path)
    return VIGNETTING_WRITERS[path.suffix.lower()](model, path)


__all__ = ["RESPONSE_READERS", "VIGNETTING_READERS", "VIGNETTING_WRITERS", "load_response", "load_vignetting",
           "read_file", "save_vignetting"]
