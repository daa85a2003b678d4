"""Image files: colour read as RGB (OpenCV's BGR converted here, exactly once), depth as float32 metres, float
images (irradiance) written as ``.npy``, ``.tiff`` or ``.exr``.

Every reader names the file and the fix when it fails, and checks a PNG's or JPEG's header before decoding it
(:func:`png_defect`, :func:`jpeg_defect`): a few corrupt bytes can claim an image of gigabytes. Writes are
atomic (:func:`radiometry.fileio.atomic_write_bytes`).
"""

from __future__ import annotations

import logging
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from radiometry.errors import ImageError, OutputError
from radiometry.fileio import atomic_write_bytes

log = logging.getLogger(__name__)
#: folders whose 16-bit images were said to use fewer than 16 bits (said once per folder, not per frame)
_NARROW_WARNED: set[str] = set()

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")


def _cv2():
    import cv2

    return cv2


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_MAX_PIXELS = 100_000_000
# deflate cannot compress better than ~1032:1, so a PNG much smaller than raw/1100 is lying about its size
_MAX_DEFLATE_RATIO = 1100


def png_defect(raw: np.ndarray | bytes) -> str | None:
    """Why a PNG cannot hold what its header claims (None when it can, or when the data is no PNG).

    Checked before decoding: a corrupt IHDR size or chunk length makes the decoder allocate and scan
    gigabytes for seconds on a file of a few bytes."""
    head = bytes(raw[:33])
    if not head.startswith(_PNG_SIGNATURE) or len(head) < 33 or head[12:16] != b"IHDR":
        return None
    size = len(raw)
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    bit_depth = max(head[24], 1)
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(head[25], 4)
    raw_bytes = width * height * channels * bit_depth / 8
    if width == 0 or height == 0 or width * height > _MAX_PIXELS or raw_bytes > size * _MAX_DEFLATE_RATIO:
        return (f"the PNG header claims {width}x{height} pixels, which this {size}-byte file cannot hold "
                "(corrupt or truncated)")
    pos = 8
    data = raw if isinstance(raw, bytes) else raw.tobytes()
    while pos + 8 <= size:
        length = int.from_bytes(data[pos:pos + 4], "big")
        if length > 2**31 - 1 or pos + 12 + length > size:
            return (f"cannot decode the PNG: chunk {data[pos + 4:pos + 8]!r} at byte {pos} claims {length} bytes "
                    f"past the end of the {size}-byte file (corrupt or truncated)")
        if data[pos + 4:pos + 8] == b"IEND":
            break
        pos += 12 + length
    return None


# Huffman-coded JPEG needs at least one bit per 8x8 block: real encoders stay below ~600:1 on flat images
_MAX_JPEG_RATIO = 4096
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def jpeg_defect(raw: np.ndarray | bytes) -> str | None:
    """Why a JPEG cannot hold the image its start-of-frame claims (None when it can, or for no JPEG):
    the decoder would fill gigabytes of a made-up size for a file of a few bytes."""
    data = bytes(raw[:65536])
    size = len(raw)
    if not data.startswith(b"\xff\xd8"):
        return None
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return None  # not a marker: let the decoder report the corruption
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):
            pos += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header before it
            return None
        length = int.from_bytes(data[pos + 2:pos + 4], "big")
        if marker in _JPEG_SOF and pos + 10 <= len(data):
            height = int.from_bytes(data[pos + 5:pos + 7], "big")
            width = int.from_bytes(data[pos + 7:pos + 9], "big")
            components = max(data[pos + 9], 1)
            if width * height > _MAX_PIXELS or width * height * components > size * _MAX_JPEG_RATIO:
                return (f"the JPEG header claims {width}x{height} pixels, which this {size}-byte file cannot hold "
                        "(corrupt or truncated)")
            return None
        pos += 2 + length
    return None


def _read_encoded(path: Path, what: str) -> np.ndarray:
    """Decode an image file (OpenCV, BGR, any depth) or raise :class:`ImageError` naming it."""
    cv2 = _cv2()
    try:
        if not path.is_file():
            raise ImageError(f"{path}: no such {what}; check the path")
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise ImageError(f"{path}: cannot read the {what} ({exc.strerror or exc}); check the path and "
                         "its permissions") from None
    if data.size == 0:
        raise ImageError(f"{path}: empty file; replace it with a valid image")
    defect = png_defect(data) or jpeg_defect(data)
    if defect is not None:
        raise ImageError(f"{path}: {defect}; replace it")
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise ImageError(f"{path}: cannot decode the {what} (corrupt, truncated or not an image); replace it")
    return img


def read_rgb(path: str | os.PathLike, *, keep_16bit: bool = False) -> np.ndarray:
    """Read a colour image as RGB uint8 ``(H, W, 3)``; grayscale files give ``(H, W)``.

    16-bit images are scaled to 8 bits (the top 8 of 16), or with ``keep_16bit`` returned as uint16 (levels
    ``value / 257``, which :meth:`radiometry.correction.Corrector.irradiance` interpolates). Raises
    :class:`ImageError` naming the file when it is missing, unreadable or truncated.
    """
    cv2 = _cv2()
    path = Path(path)
    img = _read_encoded(path, "image")
    if img.dtype == np.uint16:
        top = int(img.max()) if img.size else 0
        if top < 4096 and str(path.parent) not in _NARROW_WARNED:
            _NARROW_WARNED.add(str(path.parent))
            log.warning("%s: %s", path, _narrow_text(top) if not keep_16bit else _narrow_kept_text(top))
        if not keep_16bit:
            img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise ImageError(f"{path}: unsupported pixel type {img.dtype}; convert it to 8-bit")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        elif img.shape[2] == 1:
            img = img[:, :, 0]
        else:
            raise ImageError(f"{path}: {img.shape[2]} channels; expected 1, 3 or 4")
    return np.ascontiguousarray(img)


def _narrow_text(top: int) -> str:
    bits = max(int(top).bit_length(), 1)
    return (f"16-bit image whose values use {bits} of the 16 bits (up to {top}); it is reduced to 8 bits by keeping "
            f"the top 8 of 16, which leaves {max(top >> 8, 0) + 1} levels: save 8-bit images, or scale the data to "
            f"the full 16-bit range (x{2 ** (16 - bits)} for {bits}-bit data)")


def _narrow_kept_text(top: int) -> str:
    bits = max(int(top).bit_length(), 1)
    return (f"16-bit image whose values use {bits} of the 16 bits (up to {top}): read as levels value/257, its "
            f"brightest is level {top / 257:.1f} of 255; scale the data to the full 16-bit range "
            f"(x{2 ** (16 - bits)} for {bits}-bit data)")


def sixteen_bit_note(paths) -> str:
    """'' or a sentence when any of ``paths`` is a 16-bit image (which :func:`read_rgb` reduces to 8 bits), naming
    the first and the fix; for the errors of a fit that found too few levels in such images."""
    for path in paths:
        path = Path(path)
        try:
            img = _read_encoded(path, "image")
        except ImageError:
            continue
        if img.dtype == np.uint16:
            top = int(img.max()) if img.size else 0
            if top < 4096:
                return f"the input {path} is a {_narrow_text(top)}"
            return (f"the input {path} is a 16-bit image, reduced to 8 bits by keeping the top 8 of 16: save 8-bit "
                    "images, or scale the data to the full 16-bit range")
    return ""


def with_sixteen_bit_note(error: Exception, paths) -> str:
    """A fit's ``error`` as one line, with :func:`sixteen_bit_note` when any of ``paths`` is 16-bit: the levels a fit
    lacks are then more likely lost to the reduction to 8 bits, so the note replaces the advice of a
    :class:`~radiometry.errors.TooFewLevelsError` (to add exposures) and follows any other error."""
    from radiometry.errors import TooFewLevelsError

    note = sixteen_bit_note(paths)
    if not note:
        return str(error)
    return f"{error.finding if isinstance(error, TooFewLevelsError) else error}; {note}"


def read_depth(path: str | os.PathLike, scale: float) -> np.ndarray:
    """Read a 16-bit depth image and return float32 metres (``raw / scale``; 0 stays 0 = invalid)."""
    path = Path(path)
    if scale <= 0 or not np.isfinite(scale):
        raise ValueError(f"depth scale must be a positive number, got {scale}")
    img = _read_encoded(path, "depth image")
    if img.ndim == 3:
        raise ImageError(f"{path}: depth image has {img.shape[2]} channels; expected a single-channel 16-bit PNG")
    if img.dtype not in (np.uint16, np.float32):
        raise ImageError(f"{path}: depth must be 16-bit (got {img.dtype}); save depth as 16-bit PNG")
    depth = img.astype(np.float32) / np.float32(scale)
    depth[~np.isfinite(depth)] = 0.0
    return depth


def write_image(path: str | os.PathLike, image: np.ndarray, *, orientation: int = 1) -> Path:
    """Write an RGB (or grayscale) uint8/uint16 image atomically; the format follows the suffix. ``orientation``
    (EXIF, 1..8; 1: as stored) is written into a PNG's ``eXIf`` chunk, so that viewers turn the image as they turn the
    photo it came from (:func:`exif_orientation`); other formats are written without it."""
    cv2 = _cv2()
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    path = Path(path)
    ok, buf = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise OutputError(f"cannot encode {path} as {path.suffix}; use .png")
    data = buf.tobytes()
    if orientation != 1 and data.startswith(_PNG_SIGNATURE):
        data = _png_with_orientation(data, orientation)
    return atomic_write_bytes(path, data)


#: how a viewer shows an image of each EXIF orientation (1: as stored)
ORIENTATIONS = {1: "as stored", 2: "mirrored left-right", 3: "turned 180 degrees", 4: "mirrored top-bottom",
                5: "mirrored and turned 90 degrees", 6: "turned 90 degrees clockwise",
                7: "mirrored and turned 90 degrees", 8: "turned 90 degrees anticlockwise"}
_ORIENTATION_TAG = 0x0112


def exif_orientation(path: str | os.PathLike) -> int:
    """The EXIF orientation (1..8) a JPEG (``APP1`` Exif) or a PNG (``eXIf`` chunk) declares; 1 (as stored) when it
    declares none, for other formats and for a file that cannot be read. radiomap reads images as stored (the
    sensor's pixel order, where vignetting lives): viewers turn them by this tag."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
            if head.startswith(b"\xff\xd8"):
                return _tiff_orientation(_jpeg_exif(fh))
            if head == _PNG_SIGNATURE:
                return _tiff_orientation(_png_exif(fh))
    except (OSError, struct.error):
        pass
    return 1


def _jpeg_exif(fh) -> bytes:
    """The TIFF block of a JPEG's Exif segment (``fh`` after the first 8 bytes), b'' if none before the scan."""
    fh.seek(2)
    while True:
        marker = fh.read(2)
        if len(marker) < 2 or marker[0] != 0xFF or marker[1] in (0xD9, 0xDA):   # end of image, start of scan
            return b""
        if 0xD0 <= marker[1] <= 0xD7 or marker[1] == 0x01:   # markers without a length
            continue
        length = struct.unpack(">H", fh.read(2))[0]
        body = fh.read(length - 2)
        if marker[1] == 0xE1 and body.startswith(b"Exif\x00\x00"):
            return body[6:]


def _png_exif(fh) -> bytes:
    """The ``eXIf`` chunk of a PNG (``fh`` after the signature), b'' if none before the image data."""
    while True:
        head = fh.read(8)
        if len(head) < 8:
            return b""
        length, kind = struct.unpack(">I", head[:4])[0], head[4:]
        if kind in (b"IDAT", b"IEND"):
            return b""
        if kind == b"eXIf":
            return fh.read(length)
        fh.seek(length + 4, os.SEEK_CUR)


def _tiff_orientation(tiff: bytes) -> int:
    """The orientation tag of the first IFD of an EXIF TIFF block (1 when absent or malformed)."""
    order = {b"II": "<", b"MM": ">"}.get(tiff[:2])
    if order is None or len(tiff) < 8 or struct.unpack(order + "H", tiff[2:4])[0] != 42:
        return 1
    ifd = struct.unpack(order + "I", tiff[4:8])[0]
    if ifd + 2 > len(tiff):
        return 1
    for k in range(struct.unpack(order + "H", tiff[ifd:ifd + 2])[0]):
        entry = tiff[ifd + 2 + 12 * k: ifd + 14 + 12 * k]
        if len(entry) < 12:
            break
        tag, kind, _count = struct.unpack(order + "HHI", entry[:8])
        if tag == _ORIENTATION_TAG and kind == 3:   # SHORT
            value = struct.unpack(order + "H", entry[8:10])[0]
            return value if value in ORIENTATIONS else 1
    return 1


def _png_with_orientation(png: bytes, orientation: int) -> bytes:
    """``png`` with an ``eXIf`` chunk (after IHDR, before the image data) holding only the orientation tag."""
    tiff = b"MM\x00\x2a" + struct.pack(">I", 8) + struct.pack(">H", 1) + \
        struct.pack(">HHIHH", _ORIENTATION_TAG, 3, 1, int(orientation), 0) + struct.pack(">I", 0)
    chunk = struct.pack(">I", len(tiff)) + b"eXIf" + tiff + struct.pack(">I", zlib.crc32(b"eXIf" + tiff))
    end_of_ihdr = len(_PNG_SIGNATURE) + 8 + 13 + 4
    return png[:end_of_ihdr] + chunk + png[end_of_ihdr:]


def write_float_image(path: str | os.PathLike, data: np.ndarray) -> Path:
    """Write a float image (e.g. irradiance, RGB or one channel) as float32, atomically, in the format its suffix
    names: ``.npy`` (NumPy), ``.tiff``/``.tif`` or ``.exr`` (OpenCV, 32-bit float); OutputError naming the file
    when OpenCV cannot encode it (an OpenCV build without OpenEXR)."""
    path = Path(path)
    img = np.asarray(data).astype(np.float32)
    if path.suffix.lower() == ".npy":
        from radiometry.fileio import atomic_path

        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.save(fh, img)
        return path
    return atomic_write_bytes(path, _encode_float(path, img))


def _encode_float(path: Path, img: np.ndarray) -> bytes:
    """``img`` (float32) encoded by OpenCV in the format ``path``'s suffix names; OutputError naming ``path`` when
    this OpenCV build cannot (no OpenEXR)."""
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    cv2 = _cv2()
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    try:
        ok, buf = cv2.imencode(path.suffix, img)
    except cv2.error as exc:
        ok, buf = False, None
        reason = str(exc).strip().splitlines()[-1]
    else:
        reason = "the encoder refused"
    if not ok:
        raise OutputError(f"{path}: OpenCV cannot write 32-bit float {path.suffix.lstrip('.').upper()} ({reason}); "
                          "use --irradiance-format npy")
    return buf.tobytes()


def check_float_format(path: str | os.PathLike) -> None:
    """Refuse, before anything is written, a float image format this OpenCV build cannot write (as
    :func:`write_float_image` would on the first image)."""
    path = Path(path)
    if path.suffix.lower() != ".npy":
        _encode_float(path, np.zeros((2, 2, 3), np.float32))


def write_depth(path: str | os.PathLike, depth_m: np.ndarray, scale: float) -> Path:
    """Write float32 metres as a 16-bit PNG (``round(depth * scale)``, clipped to the uint16 range)."""
    raw = np.clip(np.round(np.nan_to_num(depth_m) * scale), 0, 65535).astype(np.uint16)
    return write_image(path, raw)


def list_images(folder: str | os.PathLike) -> list[Path]:
    """Image files in a folder, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ImageError(f"{folder}: no such folder; check the path")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file())
