"""Small deterministic sample sequences for the demo and tests, generated on first use and cached.

``sample_sequence(kind)`` renders a fixed-seed sequence once into a cache folder and returns its path;
later calls return the cached copy. The cache is in the user's cache folder, never in the checkout:
``<cache>/samples/<name>/`` where ``<cache>`` is :func:`cache_dir` (``$RADIOMAP_CACHE_DIR``, else
``$XDG_CACHE_HOME/radiomap``, else ``~/.cache/radiomap``); ``$RADIOMAP_SAMPLES_DIR`` names the samples folder itself.
The first sample written into a new cache folder says where, in one log line (WARNING, so that it shows without
``-v``: a cache the user did not ask for is not silent). A sample is rebuilt when the recipe, the radiomap version or
:data:`SAMPLE_REVISION` that made it differs (``sample.json`` records them). Generation writes into a temporary folder that is
renamed into place, so concurrent first uses are safe.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from radiometry import __version__
from radiometry.errors import OutputError
from radiometry.fileio import atomic_write_json

log = logging.getLogger(__name__)

#: name -> (kind, keyword arguments of simulate_<kind>)
SAMPLES: dict[str, tuple[str, dict[str, Any]]] = {
    "room": ("room", {"seed": 7, "n_frames": 30, "width": 320, "height": 240}),
    "paper": ("paper", {"seed": 7, "n_frames": 120, "width": 320, "height": 240}),
    "brackets": ("brackets", {"seed": 7, "width": 320, "height": 240}),
}


def cache_dir() -> Path:
    """radiomap's cache folder: ``$RADIOMAP_CACHE_DIR``, else ``$XDG_CACHE_HOME/radiomap`` (the XDG base directory
    specification), else ``~/.cache/radiomap``."""
    env = os.environ.get("RADIOMAP_CACHE_DIR")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg and Path(xdg).expanduser().is_absolute() else Path.home() / ".cache"
    return base / "radiomap"


def samples_root() -> Path:
    """Where samples are cached (see the module doc)."""
    env = os.environ.get("RADIOMAP_SAMPLES_DIR")
    if env:
        return Path(env).expanduser()
    return cache_dir() / "samples"


#: bump when the simulator's output changes for the same recipe, so that cached samples are rebuilt
SAMPLE_REVISION = 1


def _recipe(name: str) -> dict[str, Any]:
    kind, kwargs = SAMPLES[name]
    return {"name": name, "kind": kind, "kwargs": kwargs, "radiomap_version": __version__,
            "revision": SAMPLE_REVISION}


def sample_sequence(kind: str = "room", *, root: str | os.PathLike | None = None, progress: bool = False) -> Path:
    """Path of the cached sample ``kind`` (``room``, ``paper`` or ``brackets``), generating it first
    if needed (a few seconds)."""
    if kind not in SAMPLES:
        raise ValueError(f"unknown sample {kind!r}; valid names: {', '.join(SAMPLES)}")
    base = Path(root) if root is not None else samples_root()
    target = base / kind
    recipe = _recipe(kind)
    stamp_file = target / "sample.json"
    if stamp_file.is_file():
        try:
            if json.loads(stamp_file.read_text(encoding="utf-8")) == recipe:
                return target
        except (OSError, json.JSONDecodeError):
            pass
        log.info("sample %s in %s is stale; regenerating it", kind, target)
    from mapping.simulation import sequences

    try:
        if not base.is_dir():
            base.mkdir(parents=True, exist_ok=True)
            log.warning("caching the generated sample sequences in %s (RADIOMAP_CACHE_DIR moves the cache; it can be "
                        "deleted at any time)", base)
        tmp = Path(tempfile.mkdtemp(prefix=f".{kind}.", dir=base))
    except OSError as exc:
        raise OutputError(f"cannot create the sample cache in {base}: {exc}; set RADIOMAP_CACHE_DIR to a "
                          "writable folder") from None
    try:
        simulate = getattr(sequences, f"simulate_{recipe['kind']}")
        simulate(tmp, force=True, progress=progress, **recipe["kwargs"])
        atomic_write_json(tmp / "sample.json", recipe)
        if target.exists():
            shutil.rmtree(target, ignore_errors=True)
        try:
            os.replace(tmp, target)
        except OSError:
            # another process put a sample there in the meantime: use it if it is complete
            if not (target / "sample.json").is_file():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return target
