"""How much usable input makes a result: the one rule every command shares.

A reconstruction that fused, or a vignetting calibration that used, fewer than :data:`MIN_USED_FRAMES` frames
(all frames of a shorter input) or fewer than :data:`MIN_USED_FRACTION` of the frames it was given fails
with the counts and the reasons, instead of reporting success on what is left: a map of one frame out of 20,
or a vignetting model from the one frame out of 20 in which a plain region passed for a sheet, describes the
input's faults, not the scene or the lens. (``mapping.validation`` applies it to runs,
``radiometry.vignetting_calibration`` to sweeps.)
"""

from __future__ import annotations

#: a result needs at least this many usable frames (or all frames of a shorter input) ...
MIN_USED_FRAMES = 2
#: ... and at least this fraction of the frames given
MIN_USED_FRACTION = 0.1


def too_little(used: int, total: int) -> bool:
    """True when ``used`` usable frames out of ``total`` are too few to mean anything (see the module doc)."""
    if total <= 0:
        return True
    return used < min(MIN_USED_FRAMES, total) or used < MIN_USED_FRACTION * total


def rule_text() -> str:
    """The rule in words, for error messages."""
    return f"at least {MIN_USED_FRAMES} frames and {MIN_USED_FRACTION:.0%} of them"


__all__ = ["MIN_USED_FRACTION", "MIN_USED_FRAMES", "rule_text", "too_little"]
