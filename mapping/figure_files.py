"""Writing a matplotlib figure to a file (atomic; PNG, or JPEG by suffix), for :mod:`mapping.plots` and
:mod:`mapping.report` both (below them, so that neither imports the other for it)."""

from __future__ import annotations

import os
from pathlib import Path

from radiometry.fileio import atomic_path


def save_figure(fig, path: str | os.PathLike, *, dpi: int = 100) -> Path:
    """PNG, or JPEG (quality 90) for a ``.jpg``/``.jpeg`` path; atomic."""
    path = Path(path)
    fmt = (path.suffix.lstrip(".") or "png").lower()
    kwargs = {"pil_kwargs": {"quality": 90}} if fmt in ("jpg", "jpeg") else {}
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="jpeg" if fmt == "jpg" else fmt, **kwargs)
    return path
