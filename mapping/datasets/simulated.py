"""The READER of simulated sequences: folders written by :mod:`mapping.simulation` (TUM layout plus ground truth).

The other homes of made-up data: :mod:`mapping.simulation` renders and writes these folders with the simulated
camera of :mod:`radiometry.simulation`; :mod:`mapping.datasets.in_memory` is a dataset over frames already in
memory.

::

    SEQ/radiomap_sequence.json   {"format": "radiomap-sim", "version": 1, "kind": "room", "width", "height",
                                  "K", "depth_scale", "seed", "n_frames", ...}
    SEQ/rgb.txt, depth.txt, groundtruth.txt, intrinsics.txt, rgb/, depth/     (as TUM RGB-D)
    SEQ/truth/response.npz       the true camera response (radiomap model file)
    SEQ/truth/vignetting.npy     the true vignetting V, float32 (H, W, 3)
    SEQ/truth/exposures.txt      'timestamp k gain_r gain_g gain_b' per frame
    SEQ/truth/camera.json, room.json

Intrinsics and depth scale come from the manifest (an explicit option still wins).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mapping.datasets._common import _check_matrix
from mapping.datasets.tum import TUMDataset
from radiometry.errors import DatasetError

MANIFEST = "radiomap_sequence.json"
FORMAT = "radiomap-sim"
MAX_VERSION = 1


def read_manifest(path: Path) -> dict:
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read the sequence manifest ({exc.strerror})") from None
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg}); re-run the simulator") from None
    except (RecursionError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not a JSON text ({type(exc).__name__}); re-run the simulator") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise DatasetError(f"{path}: not a radiomap simulator manifest (format must be {FORMAT!r})")
    version = doc.get("version")
    if not isinstance(version, int) or not 1 <= version <= MAX_VERSION:
        raise DatasetError(f"{path}: manifest version {version!r} is not supported (up to {MAX_VERSION}); "
                           "upgrade radiomap or re-run the simulator")
    return doc


def _manifest_value(manifest: dict, key: str, path: Path, convert):
    """``convert(manifest[key])``, or DatasetError naming the manifest when the value is of the wrong kind."""
    try:
        return convert(manifest[key])
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f"{path}: {key!r} is {str(manifest[key])[:60]}, not what the simulator writes; "
                           "re-run the simulator") from None


def _matrix3(value) -> np.ndarray:
    return np.asarray(value, dtype=np.float64).reshape(3, 3)


def _positive(value) -> float:
    number = float(value)
    if not (np.isfinite(number) and number > 0):
        raise ValueError(number)
    return number


class SimulatedDataset(TUMDataset):
    """A simulated sequence: a :class:`TUMDataset` that also knows its manifest and ground-truth folder."""

    format_name = "simulated"

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)
        return (path / MANIFEST).is_file() and TUMDataset.detect(path)

    def __init__(self, path: str | Path, *, depth_scale: float | None = None, intrinsics=None,
                 frames: slice | Sequence[int] | None = None, max_difference: float = 0.02) -> None:
        root = Path(path)
        if not (root / MANIFEST).is_file():
            raise DatasetError(f"{root}: no {MANIFEST}; not a simulated sequence (try --format tum)")
        self.manifest = manifest = read_manifest(root / MANIFEST)
        source = "option" if intrinsics is not None else None
        if intrinsics is None and "K" in manifest:
            intrinsics = _check_matrix(_manifest_value(manifest, "K", root / MANIFEST, _matrix3), str(root / MANIFEST))
        given = depth_scale is not None
        if depth_scale is None:
            depth_scale = _manifest_value(manifest, "depth_scale", root / MANIFEST, _positive) \
                if "depth_scale" in manifest else 5000.0
        super().__init__(root, depth_scale=depth_scale, intrinsics=intrinsics, frames=frames,
                         max_difference=max_difference)
        if not given:    # the TUM loader took the manifest's scale for a given one
            self.depth_scale_source = "the simulator's manifest"
        if intrinsics is not None:
            self.intrinsics_source = source or "manifest"
        w, h = self.manifest.get("width"), self.manifest.get("height")
        if w is not None and h is not None and (_manifest_value(manifest, "width", root / MANIFEST, int),
                                                _manifest_value(manifest, "height", root / MANIFEST, int)) \
                != (self.width, self.height):
            raise DatasetError(f"{root / MANIFEST}: says {w}x{h} but the images are {self.width}x{self.height}; "
                               "re-run the simulator")
        n = self.manifest.get("n_frames")
        if n is not None and _manifest_value(manifest, "n_frames", root / MANIFEST, int) != len(self._all_files):
            raise DatasetError(f"{root}: the manifest lists {n} frames but rgb.txt/depth.txt pair "
                               f"{len(self._all_files)}; the sequence is incomplete, re-run the simulator")

    # ---------------------------------------------------------------- ground truth of the camera
    @property
    def truth_dir(self) -> Path:
        return self.root / "truth"

    def truth_path(self, name: str) -> Path:
        path = self.truth_dir / name
        if not path.exists():
            raise DatasetError(f"{path}: missing from the simulated sequence; re-run the simulator")
        return path

    def true_vignetting(self) -> np.ndarray:
        """The true vignetting V, float32 (H, W, 3)."""
        V = np.load(self.truth_path("vignetting.npy"), allow_pickle=False).astype(np.float32)
        if V.ndim == 2:
            V = V[:, :, None]
        if V.shape[:2] != (self.height, self.width):
            raise DatasetError(f"{self.truth_dir / 'vignetting.npy'}: {V.shape} does not match the "
                               f"{self.width}x{self.height} images")
        return V

    def true_response(self):
        """The true camera response (a :class:`radiometry.response.CameraResponse`)."""
        from radiometry.response import CameraResponse

        return CameraResponse.load(self.truth_path("response.npz"))

    def true_room(self):
        """The simulated room (:func:`mapping.simulation.load_room` of ``truth/room.json``), or None for a sequence
        without one (a white-paper sweep)."""
        path = self.truth_dir / "room.json"
        if not path.is_file():
            return None
        from mapping.simulation import load_room

        return load_room(path)

    def true_light_scales(self) -> np.ndarray | None:
        """The light's brightness factor per frame (second column of ``truth/light_scale.txt``), or None when the
        file is absent or unreadable (the light is then taken as constant)."""
        path = self.truth_dir / "light_scale.txt"
        if not path.is_file():
            return None
        try:
            return np.loadtxt(path, ndmin=2)[:, 1]
        except (OSError, ValueError, IndexError):
            return None

    def true_exposures(self) -> dict[float, np.ndarray]:
        """``{timestamp: [k, gain_r, gain_g, gain_b]}`` from ``truth/exposures.txt``."""
        path = self.truth_path("exposures.txt")
        out: dict[float, np.ndarray] = {}
        for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            if len(parts) != 5:
                raise DatasetError(f"{path}:{lineno}: expected 'timestamp k gain_r gain_g gain_b', got {line!r}")
            try:
                vals = [float(v) for v in parts]
            except ValueError:
                raise DatasetError(f"{path}:{lineno}: not numbers: {line!r}") from None
            out[vals[0]] = np.array(vals[1:])
        return out
