"""Argument checks shared by the simulator's modules: per-channel values and image sizes."""

from __future__ import annotations

from typing import Any

import numpy as np


def per_channel(value: Any, name: str, channels: int, *, low: float = 0.0, strict: bool = True) -> np.ndarray:
    """``value`` (one number or one per channel) as float64 ``(channels,)``, each finite and > ``low``
    (>= ``low`` when not ``strict``); a ValueError naming ``name`` otherwise."""
    arr = np.array(value, dtype=np.float64, ndmin=1)
    if arr.shape == (1,):
        arr = np.repeat(arr, channels)
    if arr.shape != (channels,):
        raise ValueError(f"{name} must be one number or {channels} numbers (one per channel), got {value!r}")
    if not np.all(np.isfinite(arr)) or np.any(arr < low) or (strict and np.any(arr <= low)):
        bound = f"> {low}" if strict else f">= {low}"
        raise ValueError(f"{name} must be finite and {bound}, got {value!r}")
    return arr


def check_size(width: Any, height: Any) -> tuple[int, int]:
    """``(width, height)`` as ints, each a whole number >= 2."""
    if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))) \
            or width < 2 or height < 2:
        raise ValueError(f"width and height must be whole numbers >= 2, got {width!r} x {height!r}")
    return int(width), int(height)
