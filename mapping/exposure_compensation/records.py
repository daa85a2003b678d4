"""Exposure records and their files: :class:`ExposureRecord`, the reference exposure, ``exposures.txt`` /
``exposures.json`` reading, and errors against ground truth (see :mod:`mapping.exposure_compensation`)."""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapping.exposure_compensation.masks import local_sums

log = logging.getLogger(__name__)


SOURCES = ("reference", "map", "frame", "fallback", "given")
EXPORT_REFERENCES = ("median", "first")
FILE_FORMAT = {"format": "radiomap", "kind": "exposure-estimates", "version": 1}


# --------------------------------------------------------------------------------------------------
# records
# --------------------------------------------------------------------------------------------------
@dataclass
class ExposureRecord:
    """The exposure estimate of one frame (relative to the first fused frame; one row of exposures.txt).

    k:               (3,) the exposure the frame's irradiance was divided by.
    source:          ``reference`` (the first frame, k = 1), ``map``, ``frame`` (frame to frame) or ``fallback``.
    correspondences: usable pixels of the chosen estimate (fewest over the channels; 0 for reference/fallback).
    map_k, frame_k:  (3,) the two estimates (NaN when not available), with their correspondence counts.
    map_coverage:    fraction of the frame's valid depth (off edges) on which the map agrees with it.
    disagreement:    max over channels of ``|map_k / frame_k - 1|`` (NaN unless both exist).
    reason:          why a frame fell back (or why a jump was accepted); "" otherwise.
    fuse_colour:     False when the frame's colour must not be fused (a fallback frame).
    """

    index: int
    timestamp: float
    k: np.ndarray
    source: str
    correspondences: int = 0
    map_k: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    map_correspondences: int = 0
    frame_k: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    frame_correspondences: int = 0
    map_coverage: float = 0.0
    disagreement: float = math.nan
    reason: str = ""
    fuse_colour: bool = True

    def to_dict(self) -> dict:
        def arr(a):
            return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, float)]

        return {"index": int(self.index), "timestamp": float(self.timestamp), "k": arr(self.k),
                "source": self.source, "correspondences": int(self.correspondences),
                "map_k": arr(self.map_k), "map_correspondences": int(self.map_correspondences),
                "frame_k": arr(self.frame_k), "frame_correspondences": int(self.frame_correspondences),
                "map_coverage": float(self.map_coverage),
                "disagreement": None if not np.isfinite(self.disagreement) else float(self.disagreement),
                "reason": self.reason, "fuse_colour": bool(self.fuse_colour)}


@dataclass
class _Observation:
    """One frame as the estimator sees it."""

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    pose: np.ndarray | None
    irr: np.ndarray        # f^-1(I) / V, float32 (H, W, 3) (block means when downsampled)
    usable: np.ndarray     # valid depth, off depth edges, every channel within [low, high)
    radius: int
    V: np.ndarray | None
    factor: int = 1        # downsampling of depth, irr, usable, V and K relative to rgb
    _sums: tuple[np.ndarray, np.ndarray] | None = None

    def usable_sums(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`local_sums` of ``irr`` over the usable pixels (computed once)."""
        if self._sums is None:
            self._sums = local_sums(self.irr, self.usable, self.radius)
        return self._sums


@dataclass
class _Previous:
    """What frame-to-frame estimation keeps of the last accepted frame."""

    depth: np.ndarray
    K: np.ndarray
    pose: np.ndarray
    k: np.ndarray
    sums: np.ndarray       # local sums of f^-1(I) / V over usable pixels (H, W, 3)
    count: np.ndarray      # their pixel counts (H, W)
    selected: np.ndarray   # usable pixels with a well-filled window
    V: np.ndarray | None


def resolve_reference(kind: str | float | Sequence[float], estimates: np.ndarray | None = None) -> np.ndarray:
    """A reference exposure ``(3,)`` relative to the first frame: ``"median"`` (the per-channel median of
    ``estimates`` (N, 3), ones when there are none), ``"first"`` (ones), or one / three positive numbers."""
    if isinstance(kind, str):
        if kind == "first":
            return np.ones(3)
        if kind == "median":
            est = np.ones((0, 3)) if estimates is None else np.asarray(estimates, dtype=np.float64).reshape(-1, 3)
            return np.median(est, axis=0) if len(est) else np.ones(3)
        raise ValueError(f"the exposure reference must be one of {', '.join(EXPORT_REFERENCES)} or positive "
                         f"numbers, got {kind!r}")
    try:
        values = np.asarray(kind, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise TypeError(f"the exposure reference must be 'median', 'first' or numbers, got {kind!r}") from None
    if values.size not in (1, 3) or not np.all(np.isfinite(values)) or np.any(values <= 0):
        raise ValueError(f"the exposure reference must be one positive number or three (R, G, B), got {kind!r}")
    return np.broadcast_to(values, (3,)).copy()


def parse_reference(text: str | float | Sequence[float]) -> str | float | list[float]:
    """The ``--mesh-exposure`` option (reconstruct): ``"median"``, ``"first"``, ``"0.8"`` or ``"0.8,1,1.2"`` (R, G, B);
    validated with :func:`resolve_reference`."""
    if isinstance(text, str):
        value = text.strip().lower()
        if value not in EXPORT_REFERENCES:
            try:
                numbers = [float(v) for v in value.split(",")]
            except ValueError:
                raise ValueError(f"the exposure reference must be median, first, a number or r,g,b numbers, got "
                                 f"{text!r}") from None
            value = numbers[0] if len(numbers) == 1 else numbers
        resolve_reference(value)
        return value
    resolve_reference(text)
    return text


def read_exposures(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read ``exposures.txt`` or ``exposures.json``: ``{"index", "timestamp", "k" (N, 3), "correspondences",
    "source"}`` arrays."""
    import json

    from radiometry.errors import CalibrationFileError

    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such exposure file; run radiomap reconstruct with "
                                   "--exposure-compensation")
    if path.suffix.lower() == ".json":
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise CalibrationFileError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg}); re-run the reconstruction") \
                from None
        if not isinstance(doc, dict) or doc.get("kind") != FILE_FORMAT["kind"] or "frames" not in doc:
            raise CalibrationFileError(f"{path}: not a radiomap exposure-estimates file")
        rows = doc["frames"]
        return {"index": np.array([r["index"] for r in rows], dtype=np.int64),
                "timestamp": np.array([r["timestamp"] for r in rows], dtype=np.float64),
                "k": np.array([r["k"] for r in rows], dtype=np.float64).reshape(-1, 3),
                "correspondences": np.array([r["correspondences"] for r in rows], dtype=np.int64),
                "source": np.array([r["source"] for r in rows], dtype=object)}
    idx, ts, ks, ns, srcs = [], [], [], [], []
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 7 or parts[6] not in SOURCES:
            raise CalibrationFileError(f"{path}:{lineno}: expected 'index timestamp k_r k_g k_b correspondences "
                                       f"source', got {line!r}")
        try:
            idx.append(int(parts[0]))
            ts.append(float(parts[1]))
            ks.append([float(v) for v in parts[2:5]])
            ns.append(int(parts[5]))
        except ValueError:
            raise CalibrationFileError(f"{path}:{lineno}: not numbers: {line!r}") from None
        srcs.append(parts[6])
    return {"index": np.array(idx, dtype=np.int64), "timestamp": np.array(ts), "k": np.array(ks).reshape(-1, 3),
            "correspondences": np.array(ns, dtype=np.int64), "source": np.array(srcs, dtype=object)}


# --------------------------------------------------------------------------------------------------
# evaluation against ground truth
# --------------------------------------------------------------------------------------------------
def exposure_errors(estimated: np.ndarray, truth: np.ndarray, *, use: np.ndarray | None = None,
                    skip_first: int = 0) -> dict:
    """Relative errors of per-frame exposure estimates against ground truth, both normalised to frame 0.

    estimated: ``(N, 3)`` estimates ``k_i`` (any common scale); truth: ``(N, 3)`` true effective exposures
    ``k_i * g_ic`` (or ``(N, 4)`` rows ``k, g_r, g_g, g_b`` as in ``truth/exposures.txt``). The error of
    frame ``i``, channel ``c`` is ``(est_ic / est_0c) / (true_ic / true_0c) - 1``.
    use: optional bool ``(N,)``, the frames to evaluate (e.g. non-fallback); skip_first: leave out the first
    frames (start-up) from ``median``/``max``.

    Returns ``{"errors": (N, 3) array, "median", "max", "p90" (of |error| over the evaluated frames and
    channels), "median_per_frame" (median over frames of the worst channel), "drift" (the mean signed
    error of the last quarter of the evaluated frames minus that of the first quarter, per channel: a
    trend, not noise), "final" (mean |error| of the last 5 evaluated frames), "frames" (evaluated)}``.
    """
    est = np.asarray(estimated, dtype=np.float64)
    tru = np.asarray(truth, dtype=np.float64)
    if tru.ndim == 2 and tru.shape[1] == 4:
        tru = tru[:, :1] * tru[:, 1:]
    if est.ndim != 2 or est.shape[1] != 3 or tru.shape != est.shape:
        raise ValueError(f"estimated and truth must both be (N, 3) (truth may be (N, 4) k, g_r, g_g, g_b), got "
                         f"{est.shape} and {np.shape(truth)}")
    if est.shape[0] == 0:
        raise ValueError("no frames to evaluate")
    if not (np.all(np.isfinite(est)) and np.all(est > 0) and np.all(np.isfinite(tru)) and np.all(tru > 0)):
        raise ValueError("estimated and truth must be positive finite exposures")
    err = (est / est[0]) / (tru / tru[0]) - 1.0
    sel = np.ones(est.shape[0], dtype=bool) if use is None else np.asarray(use, dtype=bool).copy()
    if sel.shape != (est.shape[0],):
        raise ValueError(f"use must be a bool array of shape ({est.shape[0]},), got {sel.shape}")
    sel[:max(int(skip_first), 0)] = False
    e = err[sel]
    if e.shape[0] == 0:
        raise ValueError("no frame left to evaluate (check use= and skip_first=)")
    a = np.abs(e)
    q = max(1, e.shape[0] // 4)
    return {"errors": err, "median": float(np.median(a)), "max": float(a.max()), "p90": float(np.percentile(a, 90)),
            "median_per_frame": float(np.median(a.max(axis=1))),
            "drift": (e[-q:].mean(axis=0) - e[:q].mean(axis=0)).tolist(),
            "final": float(a[-5:].mean()), "frames": int(e.shape[0])}
