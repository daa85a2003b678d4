"""Frame sources for a white-paper sweep: a folder, a video file, a live camera or arrays in memory, all
yielding RGB uint8 frames (:func:`open_frames` picks one)."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.errors import ImageError
from radiometry.images import IMAGE_EXTENSIONS, list_images, read_rgb

log = logging.getLogger(__name__)


class FrameSource:
    """An iterable of RGB uint8 frames (``(H, W, 3)``, or ``(H, W)`` grayscale) with a ``name``.

    ``length`` is the number of frames when known (``None`` for a live camera), for progress bars.
    """

    name: str = "frames"
    length: int | None = None

    def __iter__(self) -> Iterator[np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError


class FolderFrames(FrameSource):
    """The image files of a folder, in name order (or an explicit list of image files)."""

    def __init__(self, folder: str | os.PathLike | Sequence[str | os.PathLike]) -> None:
        if isinstance(folder, (str, os.PathLike)):
            self.paths = list_images(folder)
            self.name = str(folder)
            if not self.paths:
                raise ImageError(f"{folder}: no images ({', '.join(IMAGE_EXTENSIONS)}); check the folder")
        else:
            self.paths = [Path(p) for p in folder]
            self.name = str(self.paths[0]) if len(self.paths) == 1 else f"{len(self.paths)} images"
            if not self.paths:
                raise ValueError("the list of images is empty")
        self.length = len(self.paths)

    def __iter__(self) -> Iterator[np.ndarray]:
        for path in self.paths:
            yield read_rgb(path)


class VideoFrames(FrameSource):
    """The frames of a video file (decoded by OpenCV), converted to RGB."""

    def __init__(self, path: str | os.PathLike) -> None:
        import cv2

        self.path = Path(path)
        self.name = str(path)
        if not self.path.is_file():
            raise ImageError(f"{path}: no such video; check the path")
        cap = cv2.VideoCapture(str(self.path))
        try:
            if not cap.isOpened():
                raise ImageError(f"{path}: OpenCV cannot open the video (unknown codec or corrupt file); "
                                 "convert it to MJPG/H.264 or extract the frames to a folder")
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        finally:
            cap.release()
        self.length = count if count > 0 else None

    def __iter__(self) -> Iterator[np.ndarray]:
        """The decoded frames. When fewer decode than the container declares (``CAP_PROP_FRAME_COUNT``: a truncated
        or damaged file) one warning names the file and both counts, and the last decoded frame is left out: a frame
        cut short decodes from partial data without any error from OpenCV (MJPG: its lower part grey or shifted;
        the audit's half of a 10-frame clip gave a 6th frame 89 % of whose pixels differed from the intact decode),
        and nothing in the decoded pixels tells it apart reliably. ``decoded`` and ``dropped`` count them."""
        import cv2

        self.decoded, self.dropped = 0, 0
        cap = cv2.VideoCapture(str(self.path))
        try:
            held = None   # one frame behind: the last one is known only when the next read fails
            while True:
                ok, frame = cap.read()
                if not ok:
                    break
                if held is not None:
                    yield held
                held = _bgr_to_rgb(frame)
                self.decoded += 1
        finally:
            cap.release()
        if held is None:
            return
        if self.length is not None and self.decoded < self.length:
            self.dropped = 1
            log.warning("%s: the video declares %d frames but only %d decode (a truncated or damaged file); its last "
                        "decoded frame (%d) is left out, as it may be decoded from partial data: %d frames used",
                        self.path, self.length, self.decoded, self.decoded - 1, self.decoded - 1)
            return
        yield held


def _quiet_capture(cv2, index: int):
    """``cv2.VideoCapture(index)`` without OpenCV's own ``[ WARN:0 ...]`` lines on stderr when no camera is there
    (the one-line error below says it; the audit of 2026-11-28 saw two warning lines before it)."""
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is None:
        return cv2.VideoCapture(index)
    level = logging.getLogLevel()
    logging.setLogLevel(logging.LOG_LEVEL_SILENT)
    try:
        return cv2.VideoCapture(index)
    finally:
        logging.setLogLevel(level)


class CameraFrames(FrameSource):
    """A live camera (OpenCV capture index). Fix exposure and white balance in the camera first:
    radiomap cannot verify that through OpenCV. ``max_frames`` bounds the recording."""

    def __init__(self, index: int, *, max_frames: int | None = None, warmup: int = 10) -> None:
        if not isinstance(index, (int, np.integer)) or index < 0:
            raise ValueError(f"camera index must be a non-negative integer, got {index!r}")
        if max_frames is not None and max_frames < 1:
            raise ValueError(f"max_frames must be positive, got {max_frames}")
        self.index = int(index)
        self.max_frames = max_frames
        self.warmup = int(warmup)
        self.name = f"camera {index}"
        self.length = max_frames

    def __iter__(self) -> Iterator[np.ndarray]:
        import cv2

        cap = _quiet_capture(cv2, self.index)
        try:
            if not cap.isOpened():
                raise ImageError(f"cannot open camera {self.index}; check that it is connected and not in use, "
                                 "or record the sweep to a video or folder first")
            for _ in range(self.warmup):  # let the driver settle
                cap.read()
            n = 0
            while self.max_frames is None or n < self.max_frames:
                ok, frame = cap.read()
                if not ok:
                    break
                n += 1
                yield _bgr_to_rgb(frame)
        finally:
            cap.release()


class ArrayFrames(FrameSource):
    """Frames already in memory (RGB uint8 arrays)."""

    def __init__(self, frames: Iterable[np.ndarray], *, name: str = "arrays") -> None:
        self.frames = frames
        self.name = name
        self.length = len(frames) if hasattr(frames, "__len__") else None

    def __iter__(self) -> Iterator[np.ndarray]:
        for frame in self.frames:
            yield np.asarray(frame)


def _bgr_to_rgb(frame: np.ndarray) -> np.ndarray:
    import cv2

    if frame.ndim == 3 and frame.shape[2] == 3:
        return cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
    if frame.ndim == 3 and frame.shape[2] == 4:
        return cv2.cvtColor(frame, cv2.COLOR_BGRA2RGB)
    return frame


def open_frames(source: Any, *, max_frames: int | None = None) -> FrameSource:
    """A :class:`FrameSource` for a folder, a video file, an image file, a camera index (int or a string
    of digits), a list of image paths or a list of arrays; an existing source is returned as is."""
    if isinstance(source, FrameSource):
        return source
    if isinstance(source, (int, np.integer)) or (isinstance(source, str) and source.strip().isdigit()):
        return CameraFrames(int(source), max_frames=max_frames)
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if path.is_dir():
            return FolderFrames(path)
        if not path.exists():
            raise ImageError(f"{path}: no such folder, video or image; pass a folder of frames, a video file "
                             "or a camera index")
        if path.suffix.lower() in IMAGE_EXTENSIONS:
            return FolderFrames([path])
        return VideoFrames(path)
    if isinstance(source, np.ndarray):
        return ArrayFrames(source if source.ndim == 4 or (source.ndim == 3 and source.shape[2] not in (1, 3))
                           else [source])
    if isinstance(source, Sequence) and source and isinstance(source[0], (str, os.PathLike)):
        return FolderFrames(source)
    if isinstance(source, Iterable):
        return ArrayFrames(source)
    raise TypeError(f"source must be a folder, video, image, camera index or frames, got {type(source).__name__}")
