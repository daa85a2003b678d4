"""The project's exceptions: one base class, a subclass per area.

These are the errors radiometry raises (and mapping raises too); an error only mapping raises lives next to
the code that raises it, under the same base class (``mapping.pipeline.TrackingError``, ``mapping.validation.TooLittleFusedError``).

The CLI prints ``str(error)`` of any :class:`RadiomapError` as one line and exits with code 1, so a
message must name the file or parameter at fault and say how to fix it.
"""

from __future__ import annotations

import re

#: an error line is cut to this many characters, and every run of non-blank characters in it to TOKEN_MAX (a
#: broken list once put a 60 MB "token" into a one-line error)
LINE_MAX = 2000
TOKEN_MAX = 160


def shorten(message: str, *, line_max: int = LINE_MAX, token_max: int = TOKEN_MAX) -> str:
    """``message`` on one readable line: newlines become spaces, a token longer than ``token_max`` keeps its
    start and end around ``...(N characters)...``, and the whole is cut to ``line_max`` characters."""
    def cut(match: re.Match) -> str:
        token = match.group(0)
        return f"{token[:token_max // 2]}...({len(token):,} characters)...{token[-token_max // 4:]}"

    text = " ".join(str(message).split("\n")).replace("\r", " ")
    if len(text) > token_max:
        text = re.sub(r"\S{%d,}" % (token_max + 1), cut, text)
    if len(text) > line_max:
        text = f"{text[:line_max - 40]} ... ({len(text):,} characters in all)"
    return text


class RadiomapError(Exception):
    """Base class of every error the project raises on bad input or a failed run."""


class CalibrationFileError(RadiomapError):
    """A model file (response, vignetting, radical, DSO) is missing, corrupt or inconsistent."""


class ImageError(RadiomapError):
    """An image file is missing, unreadable, truncated or of the wrong kind."""


class DatasetError(RadiomapError):
    """An RGB-D sequence is missing, empty, inconsistent or in an unknown layout."""


class CalibrationError(RadiomapError):
    """A calibration cannot produce a trustworthy model from the data it was given."""


class AdvisedCalibrationError(CalibrationError):
    """A calibration that cannot be made: ``finding`` says what is wrong, ``advice`` the fix, kept apart so that a
    caller who knows the cause better can replace the advice without cutting the finding's text (which may hold any
    character, e.g. a folder's name)."""

    def __init__(self, finding: str, advice: str, sep: str = "; ") -> None:
        self.finding, self.advice = finding, advice
        super().__init__(f"{finding}{sep}{advice}")


class TooFewLevelsError(AdvisedCalibrationError):
    """A response fit's data constrain too few levels (e.g. 16-bit inputs that lost their levels to the reduction to
    8 bits get their own advice: :func:`radiometry.images.with_sixteen_bit_note`)."""


class ModelMismatchError(RadiomapError):
    """A model does not fit the images (resolution, aspect ratio, channel count)."""


class OutputError(RadiomapError):
    """An output cannot be written (permissions, full disk, existing file without --force)."""


class InstallationError(RadiomapError):
    """The installation or environment cannot run what was asked (e.g. ``RADIOMAP_KERNELS`` names kernels that are
    not built, or an unknown value)."""
