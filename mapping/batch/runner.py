"""Many sequences, one task each, on Ray or on local processes: :func:`run_batch`.

A task runs one command (:data:`mapping.batch.commands.COMMANDS`) on one sequence into ``OUT/<name>/`` in a worker
process (:mod:`mapping.batch.worker`); only the command's name, its plain arguments (paths, numbers, text), the
thread limit and the log file's path go to the worker, and a plain result comes back.

Resumable and idempotent: a complete results folder is skipped (unless ``force``; refused when it was made with other
options: :mod:`mapping.batch.resume`); any other (a damaged one too) is run again with the
command's ``force`` (the folder of a killed worker still holds RUNNING and a LOCK whose owner no longer runs:
:class:`mapping.export.FolderLock` takes it over and :class:`mapping.export.ResultsFolder` removes the half run's
files); a folder that a live process writes is refused by its lock, and that task fails. A failing task is reported
in one line and the others go on.

Engines: ``ray`` (a local Ray instance, or the cluster at ``address``; each task reserves ``threads`` CPUs, so Ray
places ``node CPUs // threads`` tasks on each node; Ray does not retry a task whose worker died: the next batch
does) and ``processes`` (``workers`` child processes of this one, a new process per task).
"""

from __future__ import annotations

import json
import logging
import os
import pickle
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from mapping.batch.commands import COMMANDS
from mapping.batch.resume import damage, mismatch, recorded_run, recorded_sequence, refusal
from mapping.batch.worker import thread_environment
from radiometry.errors import RadiomapError

log = logging.getLogger(__name__)

ENGINES = ("auto", "ray", "processes")
LOGS = "logs"          # OUT/logs/<name>.log: each task's output
_WORKER = "import sys; from mapping.batch.worker import main; sys.exit(main())"   # a local worker process


class BatchError(RadiomapError):
    """A batch cannot start: a bad sequence list, an engine that is not installed, no cluster at the address."""


@dataclass(frozen=True)
class Task:
    """One sequence of a batch: the results folder ``output`` (``OUT/<name>``) of ``command`` on ``sequence``;
    ``arguments`` are the keyword arguments of the command's library function (plain values)."""

    name: str
    command: str
    sequence: Path
    output: Path
    arguments: dict = field(compare=False)


@dataclass
class Outcome:
    """What became of a task: ``complete`` (run now), ``skipped`` (complete before) or ``failed`` (``error``, one
    line; the output is in ``log``)."""

    task: Task
    status: str
    error: str | None = None
    seconds: float | None = None
    log: Path | None = None
    rows: list[dict] = field(default_factory=list)


def cpu_count() -> int:
    """The cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover  (not Linux)
        return os.cpu_count() or 1


def ray_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("ray") is not None


def run_batch(tasks: Iterable[Task], out: str | os.PathLike, *, workers: int | None = None,
              threads: int | None = None, engine: str = "auto", address: str | None = None, force: bool = False,
              progress: bool = True, notify: Callable[[Outcome], None] | None = None,
              note: Callable[[str], None] | None = None) -> list[Outcome]:
    """Run every task not complete yet; returns one :class:`Outcome` per task, in the tasks' order.

    Before anything runs (unless ``force``), a :class:`BatchError` refuses the batch, in one line, when an output
    folder holds a run of another command or of another sequence, or is complete but was made with other options
    than the task's (``arguments["manifest"]``, :mod:`mapping.batch.resume`): skipping it would report old
    results as this batch's. A finished folder with a listed file missing, empty or unreadable is not complete:
    it is run again, with a line to ``note`` (default: a logged warning) naming the file.

    workers: tasks at once (default: local, one per core; on a Ray cluster, its CPUs // threads).
    threads: threads per task (default: this machine's cores // workers, at least 1).
    engine:  ``ray``, ``processes`` or ``auto`` (Ray when it is installed, else processes); ``address`` (Ray only):
             the cluster to join (``auto``, ``host:port``), None for a local Ray instance.
    force:   run complete folders again too.
    notify:  called with each outcome as it is known (skipped ones first)."""
    tasks = list(tasks)
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if engine == "auto":
        engine = "ray" if ray_available() or address is not None else "processes"
    if engine == "ray" and not ray_available():
        raise BatchError("Ray is not installed: pip install 'radiomap[cluster]' (or run with --engine processes)")
    if engine == "processes" and address is not None:
        raise BatchError("--address joins a Ray cluster; it needs --engine ray (or auto)")
    for name, value in (("workers", workers), ("threads", threads)):
        if value is not None and not (isinstance(value, int) and value >= 1):
            raise ValueError(f"{name} must be a whole number >= 1, got {value!r}")
    out = Path(out)
    plans = {task: ("run", None) if force else _plan(task) for task in tasks}
    refused = refusal([(task.output, why) for task, (what, why) in plans.items() if what == "refuse"])
    if refused is not None:
        raise BatchError(refused)
    (out / LOGS).mkdir(parents=True, exist_ok=True)
    outcomes: dict[Task, Outcome] = {}
    todo = []
    for task in tasks:
        what, why = plans[task]
        if what == "skip":
            outcomes[task] = _finish(Outcome(task, "skipped"), notify)
            continue
        if why is not None:
            (note or log.warning)(why)
        todo.append(replace(task, arguments={**task.arguments, "force": True, "progress": False}))
    if todo:
        from radiometry.progress import progress_bar

        bar = progress_bar(total=len(todo), desc=f"{todo[0].command} ({engine})", unit="sequence",
                           enabled=progress)

        def done(outcome: Outcome) -> None:
            with bar.external_write_mode():
                outcomes[outcome.task] = _finish(outcome, notify)
            bar.update(1)

        try:
            if engine == "ray":
                _run_ray(todo, out, workers=workers, threads=threads, address=address, done=done)
            else:
                _run_processes(todo, out, workers=workers or cpu_count(), threads=threads, done=done)
        finally:
            bar.close()
    return [outcomes[t] for t in tasks]


def _plan(task: Task) -> tuple[str, str | None]:
    """What a resumed batch does with a task's folder: ``("skip", None)`` (complete, of this command, sequence and
    options), ``("run", note)`` (not complete; the note names a damaged file) or ``("refuse", why)``."""
    command = COMMANDS[task.command]
    record = recorded_run(task.output)
    made_from = recorded_sequence(record)
    if record is not None and (record.get("command") not in (None, task.command) or
                               (made_from is not None and made_from != Path(os.path.abspath(task.sequence)))):
        return "refuse", mismatch(task.output, task.command, task.sequence, record, None)
    if not command.complete(task.output):
        return "run", None
    why = damage(task.output, command.outputs(task.output))
    if why is not None:
        return "run", f"{task.name}: not complete ({task.output}/{why}); running it again"
    why = mismatch(task.output, task.command, task.sequence, record, task.arguments.get("manifest"))
    return ("refuse", why) if why is not None else ("skip", None)


def _finish(outcome: Outcome, notify) -> Outcome:
    """Read the summary rows of a complete folder (a folder that does not read as complete fails the task)."""
    if outcome.status in ("complete", "skipped"):
        command = COMMANDS[outcome.task.command]
        try:
            if not command.complete(outcome.task.output):
                raise RadiomapError(f"{outcome.task.output} is not complete after the run")
            why = damage(outcome.task.output, command.outputs(outcome.task.output))
            if why is not None:
                raise RadiomapError(f"{outcome.task.output}: {why}")
            outcome.rows = command.rows(outcome.task.output)
        except (OSError, ValueError, KeyError, RadiomapError) as exc:
            outcome.status, outcome.error = "failed", f"cannot read the results: {exc}"
    if notify is not None:
        notify(outcome)
    return outcome


def _threads(threads: int | None, workers: int) -> int:
    return threads if threads is not None else max(1, cpu_count() // max(workers, 1))


def _log_path(out: Path, task: Task) -> Path:
    return out / LOGS / f"{task.name}.log"


def _start_log(path: Path, task: Task, engine: str) -> None:
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(f"--- {time.strftime('%Y-%m-%dT%H:%M:%S%z')} radiomap batch {task.command} {task.sequence} -> "
                 f"{task.output} ({engine})\n")


def _outcome(task: Task, result: dict, log_path: Path) -> Outcome:
    return Outcome(task, result["status"], error=result.get("error"), seconds=result.get("seconds"), log=log_path)


# ------------------------------------------------------------------ local processes
def _run_processes(tasks: list[Task], out: Path, *, workers: int, threads: int | None, done) -> None:
    """Up to ``workers`` child processes at once (:func:`mapping.batch.worker.main`), a new one per task, each
    started with the thread limits in its environment."""
    threads = _threads(threads, workers)
    env = {**os.environ, **thread_environment(threads)}
    pending = list(tasks)
    running: dict[subprocess.Popen, tuple[Task, Path, float]] = {}
    try:
        while pending or running:
            while pending and len(running) < workers:
                task = pending.pop(0)
                log_path = _log_path(out, task)
                _start_log(log_path, task, f"local process, {threads} thread(s)")
                with open(log_path, "ab") as log_file:
                    proc = subprocess.Popen([sys.executable, "-c", _WORKER], stdin=subprocess.PIPE,
                                            stdout=subprocess.PIPE, stderr=log_file, env=env)
                proc.stdin.write(pickle.dumps((task.command, task.arguments, threads, str(log_path), os.getcwd())))
                proc.stdin.close()
                running[proc] = (task, log_path, time.perf_counter())
            finished = [p for p in running if p.poll() is not None]
            if not finished:
                time.sleep(0.05)
                continue
            for proc in finished:
                task, log_path, started = running.pop(proc)
                done(_process_outcome(proc, task, log_path, time.perf_counter() - started))
    finally:
        for proc in running:      # interrupted: stop the workers this batch started
            proc.terminate()
        for proc in running:
            proc.wait()


def _process_outcome(proc: subprocess.Popen, task: Task, log_path: Path, seconds: float) -> Outcome:
    text = proc.stdout.read().decode("utf-8", "replace")
    proc.stdout.close()
    if proc.returncode == 0 and text.strip():
        return _outcome(task, json.loads(text.strip().splitlines()[-1]), log_path)
    if proc.returncode < 0:
        import signal

        why = f"the worker (pid {proc.pid}) died: killed by {signal.Signals(-proc.returncode).name}"
    else:
        why = f"the worker (pid {proc.pid}) exited with code {proc.returncode}"
    return Outcome(task, "failed", error=f"{why}; see {log_path}", seconds=seconds, log=log_path)


# ------------------------------------------------------------------ Ray
def _run_ray(tasks: list[Task], out: Path, *, workers: int | None, threads: int | None, address: str | None,
             done) -> None:
    """Ray tasks of :func:`mapping.batch.worker.execute`, each reserving ``threads`` CPUs, with the thread limits
    in its runtime environment; ``workers`` at most in flight; progress by ``ray.wait``."""
    import ray

    from mapping.batch.worker import execute

    started_here = not ray.is_initialized()
    if started_here:
        try:
            local = address is None and not os.environ.get("RAY_ADDRESS")     # a new Ray instance on this machine
            ray.init(address=address, num_cpus=cpu_count() if local else None,
                     include_dashboard=False, log_to_driver=False, configure_logging=False)
        except ConnectionError as exc:
            raise BatchError(f"cannot join the Ray cluster at {address!r}: {exc}") from None
    running: dict[Any, tuple[Task, Path, float]] = {}
    try:
        if threads is None:      # this machine's cores shared by the workers; one each by default on a cluster
            threads = max(1, cpu_count() // workers) if workers else 1
        workers = workers or max(1, int(ray.cluster_resources().get("CPU", 1)) // threads)
        remote = ray.remote(execute).options(num_cpus=threads, max_retries=0,
                                             runtime_env={"env_vars": thread_environment(threads)})
        pending = list(tasks)
        while pending or running:
            while pending and len(running) < workers:
                task = pending.pop(0)
                log_path = _log_path(out, task)
                _start_log(log_path, task, f"Ray, {threads} thread(s)")
                ref = remote.remote(task.command, task.arguments, threads=threads, log=str(log_path.absolute()),
                                    cwd=os.getcwd())
                running[ref] = (task, log_path, time.perf_counter())
            ready, _ = ray.wait(list(running), num_returns=1)
            for ref in ready:
                task, log_path, started = running.pop(ref)
                try:
                    outcome = _outcome(task, ray.get(ref), log_path)
                except ray.exceptions.RayError as exc:   # the worker died (killed, out of memory, node lost)
                    first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
                    outcome = Outcome(task, "failed", error=f"the Ray worker died ({type(exc).__name__}: {first})",
                                      seconds=time.perf_counter() - started, log=log_path)
                done(outcome)
    finally:
        for ref in running:       # interrupted: stop the tasks this batch started
            ray.cancel(ref, force=True)
        if started_here:
            ray.shutdown()


__all__ = ["BatchError", "ENGINES", "LOGS", "Outcome", "Task", "cpu_count", "ray_available", "run_batch"]
