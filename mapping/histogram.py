"""The colour-disagreement histogram (Alexandrov et al., IROS 2016, Fig. 9).

While fusing, every sample about to be averaged into the map is compared with the map's current colour at
the same surface point; both in 8-bit display units. The L1 distance summed over R, G, B lies in [0, 765];
it is rounded to the nearest whole level and counted in a histogram of bin width 1 (bin ``k`` holds the
distances that round to ``k``). Statistics are computed exactly from the counts: the mean of the rounded
distances, and percentiles as order statistics (the smallest ``k`` with at least ``q * N`` distances
``<= k``, NumPy's ``method="inverted_cdf"``); so the median of 1, 2, 3, 4 is 2.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from radiometry.errors import CalibrationFileError
from radiometry.fileio import atomic_write_json, json_safe, load_model_file, save_model_file

MAX_DISTANCE = 765  # 3 channels x 255 levels
BINS = MAX_DISTANCE + 1
KIND = "disagreement-histogram"


class DisagreementHistogram:
    """Counts of L1 colour distances (display units, summed over R, G, B), bins 0..765 of width 1."""

    def __init__(self, counts: np.ndarray | None = None, *, label: str = "") -> None:
        if counts is None:
            counts = np.zeros(BINS, dtype=np.int64)
        counts = np.asarray(counts)
        if counts.shape != (BINS,):
            raise ValueError(f"counts must have {BINS} bins (distances 0..{MAX_DISTANCE}), got shape {counts.shape}")
        if not np.issubdtype(counts.dtype, np.integer) and not np.all(counts == np.round(counts)):
            raise ValueError("counts must be whole numbers")
        if np.any(counts < 0):
            raise ValueError("counts must be non-negative")
        self.counts = counts.astype(np.int64)
        self.label = label

    # ---------------------------------------------------------------- accumulation
    @staticmethod
    def distances(map_display: np.ndarray, sample_display: np.ndarray) -> np.ndarray:
        """Per-row L1 distance over the channels, float32 (no rounding)."""
        a = np.asarray(map_display, dtype=np.float32)
        b = np.asarray(sample_display, dtype=np.float32)
        if a.shape != b.shape:
            raise ValueError(f"map_display and sample_display must have the same shape, got {a.shape} and {b.shape}")
        if a.ndim != 2 or a.shape[1] not in (1, 3):
            raise ValueError(f"colours must be (N, 3) (or (N, 1)) display levels, got shape {a.shape}")
        return np.abs(a - b).sum(axis=1)

    def add(self, map_display: np.ndarray, sample_display: np.ndarray) -> int:
        """Count the distances between rows of two (N, 3) display-unit arrays; returns how many were counted.

        Rows with a NaN are skipped; distances are clipped to [0, 765]."""
        return self.add_distances(self.distances(map_display, sample_display))

    def add_distances(self, distances: np.ndarray) -> int:
        """Count precomputed L1 distances (display units)."""
        d = np.asarray(distances, dtype=np.float32).ravel()
        finite = np.isfinite(d)
        if not finite.all():
            d = d[finite]
        if d.size == 0:
            return 0
        bins = np.clip(np.rint(d), 0, MAX_DISTANCE).astype(np.intp)
        self.counts += np.bincount(bins, minlength=BINS)
        return int(d.size)

    def merge(self, other: "DisagreementHistogram") -> "DisagreementHistogram":
        """Add another histogram's counts to this one (in place); returns self."""
        if not isinstance(other, DisagreementHistogram):
            raise TypeError(f"can only merge a DisagreementHistogram, got {type(other).__name__}")
        self.counts += other.counts
        return self

    def __add__(self, other: "DisagreementHistogram") -> "DisagreementHistogram":
        return DisagreementHistogram(self.counts.copy(), label=self.label).merge(other)

    # ---------------------------------------------------------------- statistics
    @property
    def total(self) -> int:
        return int(self.counts.sum())

    def __len__(self) -> int:
        return self.total

    def mean(self) -> float:
        n = self.total
        return float(np.dot(np.arange(BINS, dtype=np.float64), self.counts) / n) if n else float("nan")

    def percentile(self, q: float) -> float:
        """The ``q``-quantile (0 < q <= 1) as an order statistic of the counted distances."""
        if not 0.0 < q <= 1.0:
            raise ValueError(f"q must be in (0, 1], got {q}")
        n = self.total
        if n == 0:
            return float("nan")
        rank = int(np.ceil(q * n - 1e-9))  # 1-based rank of the order statistic
        return float(np.searchsorted(np.cumsum(self.counts), max(rank, 1)))

    def median(self) -> float:
        return self.percentile(0.5)

    def std(self) -> float:
        n = self.total
        if n == 0:
            return float("nan")
        k = np.arange(BINS, dtype=np.float64)
        m = self.mean()
        return float(np.sqrt(np.dot((k - m) ** 2, self.counts) / n))

    def stats(self) -> dict:
        """``{"count", "mean", "median", "p90", "std"}`` (NaN when empty)."""
        return {"count": self.total, "mean": self.mean(), "median": self.median(), "p90": self.percentile(0.9),
                "std": self.std()}

    def normalised(self) -> np.ndarray:
        """Counts / total (float64); zeros when empty."""
        n = self.total
        return self.counts / n if n else np.zeros(BINS)

    # ---------------------------------------------------------------- files
    def save(self, path: str | os.PathLike) -> Path:
        """Write ``.json`` (counts, statistics, label) or ``.npz`` (radiomap model file), atomically."""
        path = Path(path)
        doc = {"format": "radiomap", "kind": KIND, "version": 1, "label": self.label, "bin_width": 1,
               "max_distance": MAX_DISTANCE, "units": "L1 over R,G,B in 8-bit display levels",
               "stats": self.stats()}
        if path.suffix.lower() == ".json":
            doc["counts"] = self.counts.tolist()
            return atomic_write_json(path, doc)
        if path.suffix.lower() == ".npz":
            return save_model_file(path, KIND, {"counts": self.counts},
                                   json_safe({k: v for k, v in doc.items() if k not in ("format", "kind", "version")}))
        raise ValueError(f"histogram files are .json or .npz, got {path.name!r}")

    @classmethod
    def load(cls, path: str | os.PathLike) -> "DisagreementHistogram":
        path = Path(path)
        if path.suffix.lower() == ".npz":
            meta, arrays = load_model_file(path, KIND)
            if "counts" not in arrays:
                raise CalibrationFileError(f"{path}: no 'counts' entry; re-create the histogram")
            counts, label = arrays["counts"], meta.get("label", "")
        else:
            if not path.is_file():
                raise CalibrationFileError(f"{path}: no such histogram file; check the path")
            try:
                doc = json.loads(path.read_text(encoding="utf-8"))
            except json.JSONDecodeError as exc:
                raise CalibrationFileError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg}); re-create it") from None
            except UnicodeDecodeError:
                raise CalibrationFileError(f"{path}: a binary file, not a histogram (.json or .npz); pass the "
                                           "histogram.json or histogram.npz that a radiomap run wrote") from None
            if not isinstance(doc, dict) or doc.get("kind") != KIND or "counts" not in doc:
                raise CalibrationFileError(f"{path}: not a radiomap disagreement histogram")
            counts, label = doc["counts"], doc.get("label", "")
        try:
            return cls(np.asarray(counts), label=label)
        except ValueError as exc:
            raise CalibrationFileError(f"{path}: {exc}; re-create the histogram") from None

    def __repr__(self) -> str:
        s = self.stats()
        return (f"DisagreementHistogram({self.label!r}, count={s['count']}, mean={s['mean']:.3g}, "
                f"median={s['median']:.3g}, p90={s['p90']:.3g})")

