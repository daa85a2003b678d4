"""Exposures the camera recorded, used instead of estimating them (``radiomap reconstruct --exposures FILE``).

:class:`GivenExposures` is an :class:`~mapping.exposure_compensation.estimator.ExposureEstimator` whose
:meth:`estimate` looks the frame up instead of measuring it: ``k`` is the file's value relative to the first
fused frame's (per channel, or one value for all; :mod:`mapping.exposure_files`), recorded with source
``given``, so that ``exposures.txt`` / ``.json``, the mesh's export reference and the summary work as with
estimates. Every fused frame must have a value (the file is checked against the sequence before the run).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mapping.exposure_compensation.estimator import ExposureEstimator
from mapping.exposure_compensation.records import ExposureRecord


class GivenExposures(ExposureEstimator):
    """Exposure "estimates" from a table: ``known`` maps a frame number (:attr:`RGBDFrame.index`) to its
    exposure ``(3,)`` (any unit; only ratios matter); ``source`` names the file in the settings; ``check``: the
    verdict on its alignment (:meth:`mapping.exposure_alignment.AlignmentCheck.to_json`), recorded in them."""

    def __init__(self, response, vignetting=None, *, known: dict[int, np.ndarray], source: str = "",
                 check: dict | None = None) -> None:
        super().__init__(response, vignetting)
        if not known:
            raise ValueError("known exposures: the table is empty")
        self.known = {int(i): np.broadcast_to(np.asarray(k, dtype=np.float64), (3,)).copy() for i, k in known.items()}
        bad = [i for i, k in self.known.items() if not (np.all(np.isfinite(k)) and np.all(k > 0))]
        if bad:
            raise ValueError(f"known exposures must be finite and > 0; frame(s) {bad[:5]} are not")
        self.source = source
        self.check = check
        self._reference: np.ndarray | None = None

    def estimate(self, frame, view: Any = None, *, pose: np.ndarray | None = None) -> ExposureRecord:
        index = int(frame.index)
        if index not in self.known:
            raise KeyError(f"frame {index} has no given exposure ({self.source or 'the table'})")
        k = self.known[index]
        if self._reference is None:
            self._reference = k.copy()
        rel = k / self._reference
        record = ExposureRecord(index, float(frame.timestamp), rel, "reference" if not self.records else "given",
                                map_k=rel.copy())
        self.records.append(record)
        return record

    def settings(self) -> dict:
        doc = {"given": self.source or "table", "frames": len(self.known)}
        if self.check is not None:      # the file's alignment against the images (mapping.exposure_alignment)
            doc["alignment_check"] = self.check
        return doc


__all__ = ["GivenExposures"]
