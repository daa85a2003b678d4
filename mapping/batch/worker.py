"""One batch task in a worker process: the command's library function (:data:`mapping.batch.commands.COMMANDS`)
with the task's plain arguments, its output in the task's log file, its threads limited, and a plain result.

:func:`execute` is what a Ray task runs; :func:`main` is the local-process worker (the task pickled on stdin, the
result as one JSON line on stdout). The thread limits (:func:`thread_environment`) are set in
the worker's environment before it starts (BLAS and Numba read theirs once, at import); Open3D, whose CPU
parallelism is TBB and reads no environment variable, is limited by ``o3d.utility.set_max_threads``. This module
imports nothing heavy: Open3D is imported inside the task.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
import time
import traceback
from collections.abc import Iterator

#: the environment variables that bound the threads of OpenMP, the BLAS libraries and Numba in a process
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS", "NUMBA_NUM_THREADS")


def thread_environment(threads: int) -> dict[str, str]:
    """The environment variables that limit a worker process to ``threads`` threads (:data:`THREAD_VARIABLES`)."""
    if not (isinstance(threads, int) and threads >= 1):
        raise ValueError(f"threads must be a whole number >= 1, got {threads!r}")
    return {name: str(threads) for name in THREAD_VARIABLES}


def execute(command: str, arguments: dict, *, threads: int, log: str | None = None, cwd: str | None = None) -> dict:
    """Run ``command``'s library function with ``arguments`` in this process, limited to ``threads`` threads, its
    output (stdout, stderr, log records) appended to the file ``log``, relative paths taken from ``cwd`` (the
    folder the batch was started in; None: this process's); returns ``{"status": "complete" | "failed", "error":
    one line or None, "seconds", "pid", "threads"}``. Only a KeyboardInterrupt or SystemExit propagates."""
    start = time.perf_counter()
    with _output_to(log), _working_folder(cwd):
        try:
            _limit_threads(threads)  # imports Open3D: its failure is this sequence's one-line error too
            from mapping.batch.commands import COMMANDS

            COMMANDS[command].run(**arguments)
            status, error = "complete", None
        except Exception as exc:  # noqa: BLE001  (every failure of one sequence is reported, the others go on)
            traceback.print_exc()
            status, error = "failed", error_line(exc)
    return {"status": status, "error": error, "seconds": time.perf_counter() - start, "pid": os.getpid(),
            "threads": threads}


def error_line(exc: BaseException) -> str:
    """One line for a failed task: a radiomap error's own message, an Open3D error's text, otherwise the
    exception's type and first line (the traceback is in the task's log)."""
    from radiometry.errors import RadiomapError

    if isinstance(exc, RadiomapError):
        text = str(exc)
    elif isinstance(exc, MemoryError):
        text = "out of memory; use a larger --voxel-size, a shorter --frames range or fewer --workers"
    elif isinstance(exc, RuntimeError) and "[Open3D Error]" in str(exc):
        from mapping._open3d import open3d_message

        text = f"Open3D failed: {open3d_message(exc)}"
    else:
        text = f"{type(exc).__name__}: {exc}"
    return (text.strip().splitlines() or [type(exc).__name__])[0]


def _limit_threads(threads: int) -> None:
    os.environ.update(thread_environment(threads))       # for anything started from here
    from mapping._open3d import o3d

    o3d.utility.set_max_threads(threads)


@contextlib.contextmanager
def _working_folder(cwd: str | None) -> Iterator[None]:
    """The process works in ``cwd`` while the task runs (a reused Ray worker goes back to its own folder)."""
    before = os.getcwd()
    os.chdir(cwd or before)
    try:
        yield
    finally:
        os.chdir(before)


@contextlib.contextmanager
def _output_to(log: str | None) -> Iterator[None]:
    """stdout and stderr (the file descriptors 1 and 2, so that C++ output is caught too, and Python's streams)
    and the warnings the library logs appended to ``log`` while the task runs (None: left as they are)."""
    if log is None:
        yield
        return
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    streams = sys.stdout, sys.stderr
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    stream = open(os.dup(fd), "w", buffering=1, encoding="utf-8", errors="replace")
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    try:
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        sys.stdout = sys.stderr = stream
        root.addHandler(handler)
        yield
    finally:
        root.removeHandler(handler)
        sys.stdout, sys.stderr = streams
        stream.close()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for f in (fd, *saved):
            os.close(f)


def main() -> int:
    """The local-process worker: ``(command, arguments, threads, log, cwd)`` pickled on stdin; the result of
    :func:`execute` as one JSON line on stdout (the task's own output goes to its log)."""
    import pickle

    command, arguments, threads, log, cwd = pickle.load(sys.stdin.buffer)
    result_fd = os.dup(1)                     # the task's stdout goes to its log: the result has its own channel
    result = execute(command, arguments, threads=threads, log=log, cwd=cwd)
    with os.fdopen(result_fd, "w") as out:
        out.write(json.dumps(result) + "\n")
    return 0
