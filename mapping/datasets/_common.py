"""Shared pieces of the dataset loaders: the lazy frame list, intrinsics, frame selection, checks.

Every loader resolves its files once (cheap: text files and directory listings), then reads images only in
``__getitem__``, so a sequence of any length costs a few kilobytes until frames are asked for.
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapping.datasets.base import RGBDFrame
from radiometry.errors import DatasetError, ImageError
from radiometry.images import read_depth, read_rgb
from radiometry.textlists import read_list_text

log = logging.getLogger(__name__)

#: a depth map whose median valid depth is outside this range (metres) means a wrong depth scale
PLAUSIBLE_MEDIAN_DEPTH = (0.05, 20.0)


# --------------------------------------------------------------------------------------------------
# intrinsics
# --------------------------------------------------------------------------------------------------
def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The (3, 3) float64 pinhole matrix of ``fx, fy, cx, cy``."""
    from mapping.validation import ImplausibleValueError  # a ValueError the CLI prints as one line

    values = np.array([fx, fy, cx, cy], dtype=np.float64)
    if not np.all(np.isfinite(values)) or fx <= 0 or fy <= 0:
        raise ImplausibleValueError(f"--intrinsics must be finite with positive focal lengths, got fx={fx:g}, "
                                    f"fy={fy:g}, cx={cx:g}, cy={cy:g}; pass the camera's fx,fy,cx,cy in pixels "
                                    "(e.g. 525,525,319.5,239.5 for a 640x480 Kinect)")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _check_matrix(K: np.ndarray, source: str) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 \
            or not np.allclose(K[2], [0, 0, 1]):
        raise DatasetError(f"{source}: not a pinhole intrinsics matrix (3 x 3 with fx, fy > 0 and last row "
                           f"0 0 1), got {np.round(K, 4).tolist()}; fix the file or pass "
                           "--intrinsics fx,fy,cx,cy")
    return K


def read_intrinsics_file(path: str | os.PathLike) -> np.ndarray:
    """Read intrinsics from a file: a 3 x 3 matrix (text, whitespace or commas), one line ``fx fy cx cy``,
    or an Open3D camera JSON (``intrinsic_matrix`` column-major, as ``camera_primesense.json``)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such intrinsics file; check the path or pass --intrinsics fx,fy,cx,cy")
    text = read_text(path, "the intrinsics")
    if path.suffix.lower() == ".json" or text.lstrip().startswith("{"):
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise DatasetError(f"{path}: invalid JSON at line {exc.lineno} ({exc.msg}); fix the camera file") \
                from None
        except RecursionError:
            raise DatasetError(f"{path}: invalid JSON (nested too deeply); fix the camera file") from None
        key = next((k for k in ("intrinsic_matrix", "K") if isinstance(doc, dict) and k in doc), None)
        if key is not None:
            values = _numbers(doc[key], f"{path}: '{key}'")
            if values.size != 9:
                raise DatasetError(f"{path}: '{key}' must have 9 values, got {values.size}; fix the camera file "
                                   "or pass --intrinsics fx,fy,cx,cy")
            # Open3D stores intrinsic_matrix column-major
            return _check_matrix(values.reshape(3, 3).T if key == "intrinsic_matrix" else values.reshape(3, 3),
                                 str(path))
        if isinstance(doc, dict) and all(k in doc for k in ("fx", "fy", "cx", "cy")):
            values = _numbers([doc[k] for k in ("fx", "fy", "cx", "cy")], f"{path}: fx, fy, cx, cy")
            return _pinhole(values, str(path))
        raise DatasetError(f"{path}: JSON without 'intrinsic_matrix', 'K' or fx/fy/cx/cy; "
                           "pass --intrinsics fx,fy,cx,cy")
    rows = []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            rows.append([float(v) for v in re.split(r"[\s,]+", line) if v])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: not numbers: {line!r}; expected a 3 x 3 matrix or "
                               "'fx fy cx cy'") from None
    flat = [v for r in rows for v in r]
    if len(flat) == 9:
        return _check_matrix(np.array(flat).reshape(3, 3), str(path))
    if len(flat) == 4:
        return _pinhole(np.array(flat), str(path))
    raise DatasetError(f"{path}: expected a 3 x 3 matrix (9 numbers) or 'fx fy cx cy' (4 numbers), "
                       f"got {len(flat)} numbers")


def declared_image_size(path) -> tuple[int, int] | None:
    """The ``(width, height)`` an Open3D camera JSON declares its intrinsics for, or None (not such a file, or no
    size in it): intrinsics of another stream (a 848x480 camera file beside 640x480 frames) are otherwise used
    without a word."""
    path = Path(path)
    if path.suffix.lower() != ".json" or not path.is_file():
        return None
    try:
        doc = json.loads(read_text(path, "the intrinsics"))
        size = int(doc["width"]), int(doc["height"])
    except (ValueError, TypeError, KeyError, OverflowError, RecursionError):
        return None     # the matrix is read (and its faults reported) by read_intrinsics_file
    return size if size[0] > 0 and size[1] > 0 else None


def _numbers(value, source: str) -> np.ndarray:
    """A file's list of numbers as a flat float64 array, or DatasetError naming the file (not ValueError)."""
    try:
        values = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f"{source} must be numbers, got {str(value)[:60]}; fix the camera file or pass "
                           "--intrinsics fx,fy,cx,cy") from None
    return values


def _pinhole(values: np.ndarray, source: str) -> np.ndarray:
    """:func:`intrinsics_matrix` of ``fx fy cx cy`` read from a file: bad values name the file."""
    try:
        return intrinsics_matrix(*values)
    except ValueError as exc:
        raise DatasetError(f"{source}: {exc}; fix the file or pass --intrinsics fx,fy,cx,cy") from None


def parse_intrinsics(value) -> np.ndarray | None:
    """Turn the user's ``intrinsics`` option into a (3, 3) matrix.

    Accepts None, a (3, 3) array, four numbers ``(fx, fy, cx, cy)``, a string ``"fx,fy,cx,cy"``, or the path
    of a file understood by :func:`read_intrinsics_file`.
    """
    if value is None:
        return None
    if isinstance(value, np.ndarray) and value.shape == (3, 3):
        return _check_matrix(value, "intrinsics")
    if isinstance(value, (str, os.PathLike)):
        text = str(value)
        parts = [p for p in re.split(r"[\s,]+", text.strip()) if p]
        if not Path(text).exists():
            try:
                numbers = [float(p) for p in parts]
            except ValueError:
                numbers = None
            if numbers is not None and len(numbers) == 4:
                return intrinsics_matrix(*numbers)
            if numbers:  # numbers, but not four: not a file name either
                from mapping.validation import ImplausibleValueError

                raise ImplausibleValueError(f"--intrinsics {text!r}: {len(numbers)} number"
                                            f"{'s' if len(numbers) != 1 else ''}; give 4 numbers fx,fy,cx,cy in "
                                            "pixels (e.g. 525,525,319.5,239.5) or the path of an intrinsics file")
        return read_intrinsics_file(text)
    values = np.asarray(value, dtype=np.float64)
    if values.shape == (4,):
        return intrinsics_matrix(*values)
    if values.shape == (3, 3):
        return _check_matrix(values, "intrinsics")
    raise ValueError(f"intrinsics must be a 3x3 matrix, four numbers fx,fy,cx,cy or a file path, got {value!r}")


def intrinsics_candidates(root: Path, names: Iterable[str], *, parent: bool = False) -> list[Path]:
    """The intrinsics files a loader looks for: each of ``names`` in ``root`` (and then in its parent folder with
    ``parent``), in that order."""
    folders = (Path(root), Path(root).parent) if parent else (Path(root),)
    return [folder / name for name in names for folder in folders]


def resolve_intrinsics(option, candidates: Iterable[Path], default: Callable[[], tuple[np.ndarray, str]]
                       ) -> tuple[np.ndarray, str]:
    """A loader's intrinsics and where they came from: the ``intrinsics`` option when given ("option"), else the
    first of the format's ``candidates`` files that exists (its path), else ``default()`` (the format's own)."""
    K = parse_intrinsics(option)
    if K is not None:
        return K, "option"
    for candidate in candidates:
        if optional_file(candidate, "camera intrinsics") is not None:
            return read_intrinsics_file(candidate), str(candidate)
    return default()


# --------------------------------------------------------------------------------------------------
# frame selection and poses
# --------------------------------------------------------------------------------------------------
def select(n: int, frames: slice | Sequence[int] | None) -> list[int]:
    """Indices of a sequence of ``n`` frames picked by ``frames`` (a slice, or explicit indices)."""
    if frames is None:
        return list(range(n))
    if isinstance(frames, slice):
        if frames.step is not None and frames.step <= 0:
            raise ValueError(f"frames step must be positive, got {frames.step}")
        return list(range(n))[frames]
    idx = [int(i) for i in frames]
    bad = [i for i in idx if not -n <= i < n]
    if bad:
        raise ValueError(f"frames {bad[:5]} are out of range for a sequence of {n} frames")
    return [i % n for i in idx]


def _frames_text(frames) -> str:
    """A frame selection as the user typed it (``A:B:S``), not as Python prints a slice."""
    if isinstance(frames, slice):
        return ":".join("" if v is None else str(v) for v in (frames.start, frames.stop, frames.step)).rstrip(":")
    return str(frames)


def check_pose(pose: np.ndarray, source: str) -> np.ndarray | None:
    """A camera-to-world pose read from a file: None if it is non-finite (7-Scenes marks lost frames with
    inf), DatasetError if it is not a rigid transform."""
    pose = np.asarray(pose, dtype=np.float64)
    if not np.all(np.isfinite(pose)):
        return None
    R = pose[:3, :3]
    if not np.allclose(pose[3], [0, 0, 0, 1], atol=1e-6) or not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
        raise DatasetError(f"{source}: not a rigid camera-to-world transform (rotation not orthonormal or last "
                           "row not 0 0 0 1); fix or remove the pose")
    if np.linalg.det(R) < 0:  # orthonormal with det -1: a mirror image, which would fuse the scene mirrored
        raise DatasetError(f"{source}: the rotation is a reflection (determinant -1), not a camera pose; the "
                           "trajectory uses another handedness: negate one axis of the rotation (fix the export)")
    return pose


def optional_file(path: Path, what: str) -> Path | None:
    """``path`` when it is a regular file, None when there is nothing there, :class:`DatasetError` when it is a
    folder or something else (which would otherwise be silently ignored, e.g. a run without its ground truth)."""
    path = Path(path)
    if path.is_file():
        return path
    if not os.path.lexists(path):
        return None
    kind = "a folder" if path.is_dir() else "not a regular file (a broken link?)"
    raise DatasetError(f"{path}: the {what} is {kind}; replace it with the text file or remove it")


# --------------------------------------------------------------------------------------------------
# the lazy frame list every loader shares
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FrameFiles:
    """Where one frame lives: resolved at open time, read only on access."""

    index: int            # position in the full sequence (before frame selection)
    timestamp: float      # seconds
    rgb: Path
    depth: Path
    pose: np.ndarray | None = None       # camera-to-world, when known up front
    pose_file: Path | None = None        # or read lazily from this file (7-Scenes)
    name: str = ""                       # a short name for logs (default: the colour file's stem)


class FileSequence:
    """A dataset whose frames are image files: lazy loading, checks, frame selection and ground truth.

    Subclasses resolve the files (``FrameFiles``) and the intrinsics; this class reads them on demand.
    ``len(ds)`` and ``ds[i]`` see only the selected frames (``frames=`` range and stride applied);
    ``RGBDFrame.index`` is the frame's position in the *full* sequence, so logs and results name the
    original frame whatever the stride.
    """

    #: ``ds[i]`` may run in another thread than the caller's, ahead of the frame in use: every read builds new
    #: arrays and touches no shared state but ``_grey``, set in ``__init__`` (:mod:`mapping.prefetch`)
    thread_safe_reads = True

    format_name = "files"

    def __init__(self, root: Path, files: list[FrameFiles], K: np.ndarray, *, depth_scale: float,
                 frames: slice | Sequence[int] | None = None, name: str | None = None,
                 invalid_raw_depth: int | None = None) -> None:
        if not (isinstance(depth_scale, (int, float, np.floating)) and np.isfinite(depth_scale)
                and depth_scale > 0):
            raise ValueError(f"depth_scale must be a positive number, got {depth_scale!r}")
        self.root = Path(root)
        self.name = name or self.root.name
        self.depth_scale = float(depth_scale)
        self._invalid_raw_depth = invalid_raw_depth
        self._all_files = files
        self._grey: bool | None = None   # grey or colour images: set by the first frame read
        if not files:
            raise DatasetError(f"{self.root}: the {self.format_name} sequence has no frames; check the folder")
        picked = select(len(files), frames)
        if not picked:
            raise DatasetError(f"{self.root}: the frame selection {_frames_text(frames)} leaves no frames out of "
                               f"{len(files)}; widen --frames")
        if isinstance(frames, slice) and frames.stop is not None and frames.stop > len(files):
            log.warning("%s: --frames %s reaches past the sequence's %d frames; cut to %s", self.root,
                        _frames_text(frames), len(files), _frames_text(slice(frames.start, len(files), frames.step)))
        self._files = [files[i] for i in picked]
        self.K = np.asarray(K, dtype=np.float64)
        first = self._read(self._files[0])
        self.height, self.width = first.rgb.shape[:2]
        self._check_intrinsics(first)

    # ---------------------------------------------------------------- protocol
    def __len__(self) -> int:
        return len(self._files)

    def __getitem__(self, index: int) -> RGBDFrame:
        n = len(self._files)
        if not isinstance(index, (int, np.integer)):
            raise TypeError(f"dataset index must be an integer, got {type(index).__name__}")
        if not -n <= index < n:
            raise IndexError(f"frame {index} is out of range for {n} frames")
        frame = self._read(self._files[index % n])
        if (frame.height, frame.width) != (self.height, self.width):
            raise DatasetError(f"{self._files[index % n].rgb}: {frame.width}x{frame.height} pixels while the "
                               f"sequence starts at {self.width}x{self.height}; all frames must have one size")
        return frame

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray] | None:
        stamps, poses = [], []
        for f in self._files:
            pose = self._pose_of(f)
            if pose is not None:
                stamps.append(f.timestamp)
                poses.append(pose)
        if not poses:
            return None
        return np.asarray(stamps, dtype=np.float64), np.stack(poses)

    @property
    def timestamps(self) -> np.ndarray:
        return np.array([f.timestamp for f in self._files])

    @property
    def total_frames(self) -> int:
        """Frames of the whole sequence (before ``frames`` selected some)."""
        return len(self._all_files)

    @property
    def frame_files(self) -> list[FrameFiles]:
        """The selected frames' files (nothing is read)."""
        return list(self._files)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({str(self.root)!r}, frames={len(self)}, {self.width}x{self.height}, "
                f"depth_scale={self.depth_scale:g})")

    # ---------------------------------------------------------------- reading
    def _pose_of(self, f: FrameFiles) -> np.ndarray | None:
        if f.pose is not None:
            return f.pose
        if f.pose_file is not None:
            return read_pose_matrix_file(f.pose_file)
        return None

    def _read(self, f: FrameFiles) -> RGBDFrame:
        try:
            rgb = read_rgb(f.rgb)
            depth = read_depth(f.depth, self.depth_scale)
        except ImageError as exc:
            raise DatasetError(f"{exc} (frame {f.index} of {self.root})") from None
        grey = rgb.ndim == 2
        if getattr(self, "_grey", None) is None:
            self._grey = grey  # the first frame read (frame 0 of the selection) sets the sequence's kind
            if grey:
                log.info("%s: grey (single-channel) colour images; fused as R = G = B", self.root)
        elif grey != self._grey:
            kinds = ("grey (single-channel)", "colour") if grey else ("colour", "grey (single-channel)")
            raise DatasetError(f"{f.rgb}: a {kinds[0]} image in a sequence of {kinds[1]} images (frame {f.index} of "
                               f"{self.root}); convert it or remove the frame: one map cannot mix both")
        if grey:
            rgb = np.repeat(rgb[:, :, None], 3, axis=2)
        if self._invalid_raw_depth is not None:
            depth[depth >= np.float32(self._invalid_raw_depth / self.depth_scale) - 1e-6] = 0.0
        if rgb.shape[:2] != depth.shape:
            raise DatasetError(
                f"{f.rgb} is {rgb.shape[1]}x{rgb.shape[0]} but its depth {f.depth} is "
                f"{depth.shape[1]}x{depth.shape[0]}; colour and depth must be registered at one resolution "
                "(resize or register them first)")
        self._check_depth_range(depth, f.depth)
        return RGBDFrame(index=f.index, timestamp=f.timestamp, rgb=rgb, depth=depth, K=self.K,
                         pose=self._pose_of(f), name=f.name or f.rgb.stem)

    def _check_depth_range(self, depth: np.ndarray, path: Path) -> None:
        sample = depth[::4, ::4]
        valid = sample[sample > 0]
        if valid.size < 16:
            return  # an empty frame (lens covered, all out of range) is for tracking to reject, not the loader
        median = float(np.median(valid))
        lo, hi = PLAUSIBLE_MEDIAN_DEPTH
        if not lo <= median <= hi:
            raw = median * self.depth_scale
            # the usual scale that puts the median nearest to a typical indoor 2 m
            suggestion = min((1000.0, 5000.0, 1.0, 100.0, 10000.0), key=lambda s: abs(np.log(raw / s / 2.0)))
            raise DatasetError(
                f"{path}: median depth {median:.3g} m with depth scale {self.depth_scale:g} is implausible for an "
                f"RGB-D camera (expected {lo:g}..{hi:g} m); pass the right --depth-scale "
                f"(raw units per metre, e.g. --depth-scale {suggestion:g})")

    def _check_intrinsics(self, frame: RGBDFrame) -> None:
        """The principal point at opening (the field of view is checked before a run: mapping.validation)."""
        from mapping.validation import principal_point_problem

        source = getattr(self, "intrinsics_source", None)
        option = getattr(self, "intrinsics_option", None)
        if source == "option":   # --intrinsics FILE: a camera JSON of another stream is as wrong given as found
            source = f"--intrinsics {option}" if isinstance(option, (str, os.PathLike)) else None
            path = option if source is not None else None
        else:
            path = source
        declared = declared_image_size(path) if path is not None else None
        if declared is not None and declared != (self.width, self.height):
            raise DatasetError(f"{source}: its intrinsics are for {declared[0]}x{declared[1]} images, the frames "
                               f"are {self.width}x{self.height}; pass --intrinsics fx,fy,cx,cy of the "
                               f"{self.width}x{self.height} stream, or "
                               + ("that stream's camera file" if source.startswith("--") else
                                  "put that stream's camera file there"))
        problem = principal_point_problem(self.K, self.width, self.height)
        if problem:
            raise DatasetError(f"{self.root}: {problem}")


# --------------------------------------------------------------------------------------------------
# small text-file readers that report file and line
# --------------------------------------------------------------------------------------------------
def read_text(path: Path, what: str) -> str:
    """A list or matrix file's text (:func:`radiometry.textlists.read_list_text`: byte-order marks, CRLF,
    non-UTF-8 names), or :class:`DatasetError` naming the file and ``what`` it holds when it cannot be read."""
    try:
        return read_list_text(path)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read {what} ({exc.strerror or exc}); check the file") from None


def read_pose_matrix_file(path: Path) -> np.ndarray | None:
    """A 4 x 4 camera-to-world matrix in a text file (7-Scenes ``frame-NNNNNN.pose.txt``)."""
    rows = []
    for lineno, line in enumerate(read_text(path, "the pose").splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = [float(v) for v in line.split()]
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: not numbers: {line.strip()!r}; a pose file holds a 4 x 4 "
                               "matrix") from None
        if len(row) != 4:
            raise DatasetError(f"{path}:{lineno}: {len(row)} values; a pose file holds 4 rows of 4 numbers")
        rows.append(row)
    if len(rows) != 4:
        raise DatasetError(f"{path}: {len(rows)} rows; a pose file holds a 4 x 4 matrix")
    return check_pose(np.array(rows), str(path))


def data_lines(path: Path, what: str):
    """``(line number, stripped line, its fields)`` of each line of a text list that is not blank or a ``#``
    comment (read by :func:`read_text`, which names ``what`` in its errors)."""
    for lineno, line in enumerate(read_text(path, what).splitlines(), 1):
        line = line.strip()
        if line and not line.startswith("#"):
            yield lineno, line, line.split()


def read_stamped_list(path: Path) -> list[tuple[float, str, int]]:
    """TUM ``rgb.txt`` / ``depth.txt``: ``timestamp filename`` per line, ``#`` comments (read by
    :func:`radiometry.textlists.read_list_text`: byte-order marks, CRLF, non-UTF-8 names).

    Returns ``(timestamp, filename, line number)`` tuples sorted by timestamp, repeated lines dropped
    (:func:`tidy_stamped`, which warns with the counts); malformed lines raise :class:`DatasetError` with
    file and line."""
    out = []
    for lineno, line, parts in data_lines(path, "the frame list"):
        if len(parts) != 2:
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp filename', got {len(parts)} entries "
                               f"({line!r})")
        try:
            stamp = float(parts[0])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: timestamp {parts[0]!r} is not a number") from None
        if not np.isfinite(stamp):
            raise DatasetError(f"{path}:{lineno}: timestamp {parts[0]!r} is not finite")
        out.append((stamp, parts[1], lineno))
    return tidy_stamped(out, path)


def tidy_stamped(rows: list[tuple[float, str, int]], path) -> list[tuple[float, str, int]]:
    """``(timestamp, name, line)`` rows in time order: rows out of order are sorted (other tools append or merge
    lists), a timestamp or a file listed again is dropped (the first line wins); one warning says what was done,
    with counts, so that no frame is reordered or dropped silently."""
    late = sum(1 for a, b in zip(rows, rows[1:]) if b[0] < a[0])
    kept: list[tuple[float, str, int]] = []
    stamps: set[float] = set()
    names: dict[str, int] = {}
    repeated_stamp = repeated_name = 0
    for row in sorted(rows, key=lambda r: (r[0], r[2])):
        if row[0] in stamps:
            repeated_stamp += 1
        elif row[1] in names:
            repeated_name += 1
        else:
            stamps.add(row[0])
            names[row[1]] = row[2]
            kept.append(row)
    notes = []
    if late:
        notes.append(f"{late} line(s) out of time order (sorted by timestamp)")
    if repeated_stamp:
        notes.append(f"{repeated_stamp} line(s) repeating a timestamp (dropped; the first line kept)")
    if repeated_name:
        notes.append(f"{repeated_name} line(s) listing a file again at another time (dropped; the first kept)")
    if notes:
        log.warning("%s: %s; %d of %d frames kept", path, "; ".join(notes), len(kept), len(rows))
    return kept
