"""Array files: the check that model arrays hold real numbers, and the reader of single-array ``.npy`` files.

Both read with ``allow_pickle=False`` and name the file (and the array) in every error; the dtype of an array
that NumPy refuses to load is read from its header so that the message can say what it holds.
"""

from __future__ import annotations

import os
import struct
import tokenize
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from radiometry.errors import CalibrationFileError

_NPY_MAGIC = b"\x93NUMPY"


def refuse_bare_npy(path: Path, kind: str, *, bare: bool = False) -> None:
    """:class:`CalibrationFileError` when ``path`` is a single ``.npy`` array (its magic bytes, or ``bare``) where a
    model archive (``.npz``) is needed: np.load would return the array itself, not an archive."""
    if not bare:
        try:
            with open(path, "rb") as fh:
                bare = fh.read(len(_NPY_MAGIC)) == _NPY_MAGIC
        except OSError:
            return  # np.load reports it
    if bare:
        hint = " (a V array is read from a .npy file by reconstruct/correct --vignetting and compare --vignetting-lut)" \
            if kind == "vignetting" else ""
        raise CalibrationFileError(f"{path}: a bare .npy array, not a radiomap {kind} model file; pass the {kind} "
                                   f".npz that radiomap wrote{hint}")


# Model arrays hold real numbers: bool, signed and unsigned integers, floats. Anything else (complex, whose
# imaginary part a cast would drop; pickled objects; text; structured records; dates) is refused, here only.
_REAL_KINDS = "biuf"
_KIND_NAMES = {"c": "complex", "O": "pickled Python-object", "U": "text", "S": "byte-string", "V": "structured",
               "M": "date-time", "m": "time-delta"}


def check_real_arrays(path: str | os.PathLike, dtypes: Mapping[str | None, np.dtype], fix: str) -> None:
    """Raise :class:`CalibrationFileError` naming ``path`` (and the array) if a dtype is not real numeric.

    ``dtypes`` maps array names (None for a file holding one array) to their dtypes; ``fix`` ends the message.
    Every model loader goes through here: :func:`radiometry.fileio.load_model_file`, :func:`load_array_file`
    (``.npy``)."""
    for name, dtype in dtypes.items():
        dtype = np.dtype(dtype)
        if dtype.kind in _REAL_KINDS and dtype.fields is None:
            continue
        what = f"array {name!r} holds" if name is not None else "holds"
        kind = "structured" if dtype.fields is not None else _KIND_NAMES.get(dtype.kind, "non-numeric")
        raise CalibrationFileError(f"{path}: {what} {kind} values ({dtype}) where real numbers (bool, integer or "
                                   f"float) are needed; {fix}")


def _npy_header_dtype(fh) -> np.dtype | None:
    """The dtype in a ``.npy`` header (without reading the data); None if the header cannot be parsed."""
    fmt = np.lib.format
    try:
        major, _minor = fmt.read_magic(fh)
        header = fmt.read_array_header_1_0 if major == 1 else fmt.read_array_header_2_0
        return np.dtype(header(fh)[2])
    except Exception:  # noqa: BLE001 - best effort: the caller falls back to its generic message
        return None


def npz_header_dtypes(path: Path) -> dict[str, np.dtype]:
    """Member name -> dtype of the arrays of an ``.npz`` whose headers can be read (corrupt members skipped)."""
    out: dict[str, np.dtype] = {}
    try:
        with zipfile.ZipFile(path) as archive:
            for member in archive.namelist():
                with archive.open(member) as fh:
                    dtype = _npy_header_dtype(fh)
                if dtype is not None:
                    out[member.removesuffix(".npy")] = dtype
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, zlib.error, NotImplementedError, RuntimeError):
        pass
    return out


def load_array_file(path: str | os.PathLike, *, fix: str) -> np.ndarray:
    """Read a single-array ``.npy`` file (no pickle) holding real numbers; :class:`CalibrationFileError` naming
    the file and ending with ``fix`` otherwise."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such file; {fix}")
    try:
        array = np.load(path, allow_pickle=False)
    except ValueError as exc:
        try:
            with open(path, "rb") as fh:
                dtype = _npy_header_dtype(fh)
        except OSError:
            dtype = None
        if dtype is not None:
            check_real_arrays(path, {None: dtype}, fix)
        raise CalibrationFileError(f"{path}: not a NumPy .npy array or corrupt ({type(exc).__name__}); {fix}") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, struct.error, UnicodeDecodeError, OverflowError,
            tokenize.TokenError, SyntaxError, MemoryError) as exc:
        raise CalibrationFileError(f"{path}: not a NumPy .npy array or corrupt ({type(exc).__name__}); {fix}") from None
    if not isinstance(array, np.ndarray):  # an .npz archive under a .npy name
        array.close()
        raise CalibrationFileError(f"{path}: an .npz archive of several arrays, not one .npy array; {fix}")
    check_real_arrays(path, {None: array.dtype}, fix)
    return array
