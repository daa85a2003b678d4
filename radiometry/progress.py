"""The one place progress bars are made: tqdm on stderr, drawn only for a person watching a terminal.

Every loop over frames or images takes its bar from :func:`progress_bar`. The convention is tqdm's own
(``disable=None``): a bar is drawn only when its stream is a terminal, so a run whose stderr goes to a
pipe or a log file writes no carriage-return redraws there; ``enabled=False`` (the commands'
``--no-progress``, the library's ``progress=False``) turns it off on a terminal too. A disabled bar is
still a ``tqdm`` object: ``update``, ``set_postfix`` and ``close`` do nothing (it does not count either) and
iterating it passes the items through, so callers never branch on whether it is drawn.
"""

from __future__ import annotations

import sys
from typing import IO, Any, Iterable

__all__ = ["progress_bar"]


def progress_bar(iterable: Iterable[Any] | None = None, *, total: int | None = None, desc: str,
                 unit: str = "frame", enabled: bool = True, leave: bool = True, file: IO[str] | None = None):
    """A ``tqdm`` bar over ``iterable`` (or updated by hand up to ``total``) on ``file`` (default: stderr).

    Drawn only when ``enabled`` and ``file`` is a terminal (``file.isatty()``); otherwise silent. ``leave=False``
    clears the bar when it closes (for loops followed by their own summary).
    """
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit=unit, leave=leave, dynamic_ncols=True,
                file=sys.stderr if file is None else file, disable=None if enabled else True)
