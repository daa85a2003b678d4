"""Frames read ahead in a background thread while the pipeline works on the current one (issue 33).

:class:`FramePrefetcher` reads ``dataset[i]`` (file reads, PNG/JPEG decoding by OpenCV, the loader's checks) for
the frames after the one :func:`mapping.pipeline.reconstruct` is tracking, fusing and casting: OpenCV's decoding
and NumPy's conversions release the GIL, as do Open3D's and radiomap's kernels, so loading overlaps the rest of
the loop instead of adding to it. The frames are the very objects the dataset returns, in order, so a run reads
the same data and gets the same results as the serial path (``tests/test_prefetch.py``).

- Order: :meth:`FramePrefetcher.get` hands out frame 0, 1, 2, ... and refuses any other order.
- Bounded: at most ``ahead`` frames wait read (``ahead`` 1 by default: with the one being read and the one being
  worked on, two frames beyond the pipeline's), however slow the rest of the loop is.
- Errors: an exception raised while reading frame ``i`` (a :class:`radiometry.errors.DatasetError` naming the
  file, a ``KeyboardInterrupt`` raised by a dataset, anything else) is kept and raised, the same object, by
  ``get(i)``: at the frame where the serial path raises it, with the same one-line message; the frames before it
  are handed out first. Frames after it are not read.
- Stopping: :meth:`FramePrefetcher.close` (also on leaving a ``with`` block: Ctrl-C, tracking lost for good, an
  error anywhere) stops the thread and waits for it: at most the frame being read is finished, none is started,
  no thread is left behind.

``ahead=0`` (``reconstruct(prefetch=0)``) reads each frame in the caller's thread when asked for: the serial path.
"""

from __future__ import annotations

import collections
import threading

THREAD_NAME = "radiomap-prefetch"


def check_ahead(ahead, name: str = "prefetch") -> int:
    """``ahead`` (frames read ahead) as a whole number >= 0, or ValueError naming ``name``."""
    if not isinstance(ahead, int) or isinstance(ahead, bool) or ahead < 0:
        raise ValueError(f"{name} must be a whole number >= 0 (frames read ahead in a background thread; 0 reads "
                         f"each frame in the caller's thread), got {ahead!r}")
    return ahead


class FramePrefetcher:
    """``dataset[0 .. len(dataset) - 1]`` read ahead by one background thread (module doc); ``ahead`` >= 0 frames
    kept read (0: no thread, each frame read by :meth:`get`)."""

    def __init__(self, dataset, ahead: int = 1) -> None:
        check_ahead(ahead, "ahead")
        self.dataset = dataset
        self.ahead = ahead
        self._n = len(dataset)
        self._next = 0                       # the frame get() hands out next
        self._ready: collections.deque = collections.deque()   # (position, frame or None, exception or None)
        self._cond = threading.Condition()
        self._stop = False
        self.stalled = threading.Event()     # set whenever the thread waits for room (tests: the bound, no sleeps)
        self._thread = None
        if ahead:
            self._thread = threading.Thread(target=self._run, name=THREAD_NAME, daemon=True)
            self._thread.start()

    # ---------------------------------------------------------------- the caller's side
    def __len__(self) -> int:
        return self._n

    def get(self, i: int):
        """Frame ``i``, which must be the next one (0, 1, 2, ...); raises what reading it raised."""
        if i != self._next:
            raise ValueError(f"frames are read ahead in order: asked for frame {i}, the next one is {self._next}")
        if i >= self._n:
            raise IndexError(f"frame {i} is out of range for {self._n} frames")
        if self._thread is None:
            if self._stop:
                raise RuntimeError("the frame prefetcher is closed")
            self._next += 1
            return self.dataset[i]
        with self._cond:
            while not self._ready:
                if self._stop:
                    raise RuntimeError("the frame prefetcher is closed")
                self._cond.wait()
            position, frame, error = self._ready.popleft()
            self._cond.notify_all()
        self._next += 1
        if error is not None:
            self.close()     # nothing after a failed frame is read
            raise error
        assert position == i
        return frame

    def stop(self) -> None:
        """Stop reading ahead without waiting for the thread (:meth:`close` waits). Idempotent."""
        with self._cond:
            self._stop = True
            self._ready.clear()
            self._cond.notify_all()

    def close(self) -> None:
        """Stop reading ahead and wait for the thread (it finishes at most the frame it is reading). Idempotent."""
        self.stop()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join()

    @property
    def alive(self) -> bool:
        """Whether the background thread is still running."""
        return self._thread is not None and self._thread.is_alive()

    def __enter__(self) -> "FramePrefetcher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---------------------------------------------------------------- the thread
    def _run(self) -> None:
        for i in range(self._n):
            with self._cond:
                while len(self._ready) >= self.ahead and not self._stop:
                    self.stalled.set()
                    self._cond.wait()
                if self._stop:
                    return
            try:
                item = (i, self.dataset[i], None)
            except BaseException as exc:   # noqa: BLE001 - handed to the caller's thread, raised there by get(i)
                item = (i, None, exc)
            with self._cond:
                if self._stop:
                    return
                self._ready.append(item)
                self._cond.notify_all()
            if item[2] is not None:
                return


__all__ = ["FramePrefetcher", "THREAD_NAME", "check_ahead"]
