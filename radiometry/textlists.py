"""Text lists written by other tools, read tolerantly: one reader for every list the project reads.

TUM ``rgb.txt`` / ``depth.txt`` / ``groundtruth.txt``, associations, bracket ``times.txt`` / ``image_list.txt``,
Redwood ``.log`` and ``rgbd.match``, 7-Scenes pose files and intrinsics come from cameras, scripts and editors
on every system. :func:`read_list_text` reads them all the same way:

- a byte-order mark is removed (UTF-8) or honoured (UTF-16 / UTF-32, as Windows tools write them);
- line ends may be LF, CRLF or CR (``str.splitlines``);
- bytes that are not UTF-8 (a file name in Latin-1 or CP-1252) are kept as surrogate escapes, exactly as
  Python decodes such names from the file system (``os.fsdecode``), so the name opens the same file on disk.
  A warning names the file and the number of such lines.

What the lines mean (columns, comments, order, duplicates) is for each format's reader.
"""

from __future__ import annotations

import codecs
import logging
import os
from pathlib import Path

from radiometry.errors import DatasetError

log = logging.getLogger(__name__)

#: byte-order marks and the encodings they announce (UTF-32 before UTF-16: its LE mark starts with UTF-16's)
BOMS = ((codecs.BOM_UTF32_LE, "utf-32-le"), (codecs.BOM_UTF32_BE, "utf-32-be"), (codecs.BOM_UTF8, "utf-8"),
        (codecs.BOM_UTF16_LE, "utf-16-le"), (codecs.BOM_UTF16_BE, "utf-16-be"))


def decode_list(data: bytes, source: str = "text") -> str:
    """``data`` as text (see the module doc); ``source`` names it in the warning about non-UTF-8 bytes and in the
    :class:`DatasetError` for data that is no text at all (NUL bytes; UTF-16/32 that does not decode)."""
    not_text = DatasetError(f"{source}: not a text file (NUL bytes or undecodable characters); a list must be "
                            "plain text with one entry per line")
    for bom, encoding in BOMS:
        if data.startswith(bom):
            data = data[len(bom):]
            if encoding != "utf-8":
                text = data.decode(encoding, errors="replace")
                if "\ufffd" in text or "\x00" in text:
                    raise not_text
                return text
            break
    if b"\x00" in data:
        raise not_text
    text = data.decode("utf-8", errors="surrogateescape")
    if any("\udc80" <= ch <= "\udcff" for ch in text):
        bad = sum(1 for line in text.splitlines() if any("\udc80" <= ch <= "\udcff" for ch in line))
        log.warning("%s: %d line(s) are not UTF-8 (e.g. Latin-1 file names); their bytes are kept as they are, so "
                    "the names still open the files on disk", source, bad)
    return text


def read_list_text(path: str | os.PathLike) -> str:
    """The text of a list file (see the module doc); ``OSError`` as :meth:`pathlib.Path.read_text` raises it,
    :class:`DatasetError` for a file that is no text."""
    path = Path(path)
    return decode_list(path.read_bytes(), str(path))


def list_lines(path: str | os.PathLike) -> list[tuple[int, str]]:
    """``(line number, line)`` of a list file, line ends removed (LF, CRLF or CR)."""
    return list(enumerate(read_list_text(path).splitlines(), 1))


__all__ = ["BOMS", "decode_list", "list_lines", "read_list_text"]
