"""Results folders that ``--force`` replaces as one set: the previous result stands until the new one is complete.

:class:`StagedResultsFolder` is a :class:`mapping.export.ResultsFolder` that, when ``force`` is given over a COMPLETE
previous result (:meth:`StagedResultsFolder._previous_complete`), writes the new run into a staging folder inside
OUT (:attr:`~mapping.export.ResultsFolder.path` points there: the run sees its usual layout, ``RUNNING`` marker
and all) and publishes it with :func:`radiometry.fileio.publish_set` when :meth:`~StagedResultsFolder.complete` is
called: every staged file and folder is renamed into OUT (a folder of the previous result moved away first), the
previous result's files and folders that the new one does not replace are moved away in the same commit, the
:attr:`~StagedResultsFolder.primary` record last, and a journal lists the renames until the commit point (a SIGKILL
during them is rolled back by the next run in OUT, :func:`radiometry.fileio.remove_strays`). An interruption at any
moment (Ctrl-C, SIGKILL, a failure) therefore leaves the previous result or the new one, never neither, and a
completed run leaves nothing of the previous one behind. The user's files in OUT are never touched; those in a
results folder of the previous run (a comparison's method folder) are carried into the new one (hard links).

A first run, or one over an incomplete (interrupted) result, is written in place as before: there is nothing
complete to keep.

Subclasses: :class:`ReconstructionFolder` (``reconstruct``), :class:`mapping.compare.ComparisonFolder`,
:class:`mapping.demo.DemoFolder`, :class:`mapping.simulation.sequences.SequenceFolder`;
:class:`mapping.self_calibration.SelfCalibrationFolder` uses ``publish_set`` directly (files only).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
from pathlib import Path

from mapping.export import (LOCK_NAME, MANIFEST, RESULT_NAMES, RUNNING_MARKER, FolderLock, ResultsFolder,
                            _is_pattern, _manifest_entries, is_complete)
from radiometry.fileio import TEMP_TAG, atomic_write_json

log = logging.getLogger(__name__)


class StagedResultsFolder(ResultsFolder):
    """A results folder whose ``force`` over a complete previous result stages the new run (module doc)."""

    #: the record published last: while it is the previous one, the previous result is in place
    primary = "metrics.json"

    def __init__(self, path: str | os.PathLike, *, force: bool = False) -> None:
        self._publication = None     # the open publish_set context
        self._set = None             # its FileSet
        self._staging = False        # force over a complete result: the new run is staged
        self._completed = False
        self._subs: list[ResultsFolder] = []
        self.final_path = Path(path)
        super().__init__(path, force=force)
        if self._staging:
            from radiometry.fileio import publish_set

            try:
                self._publication = publish_set(self.final_path / self.primary)
                self._set = self._publication.__enter__()
                self.path = self._set.path(self.final_path / self.primary).parent
                self._before = {}
                super()._mark_running()   # inside the staging folder: the run sees the layout it always sees
            except BaseException:
                self.release()
                raise

    def _previous_complete(self) -> bool:
        """The folder holds a complete result of this kind (kept until the new one is published)."""
        return is_complete(self.path)

    def _remove_previous_run(self) -> None:
        if not self._previous_complete():
            super()._remove_previous_run()
            return
        for name in self._previous_folders(self.path):   # a live run in a results folder of the previous result refuses
            if not (self.path / name).is_symlink():
                FolderLock(self.path / name).release()
        self._staging = True                     # kept until the new run is published (complete)

    def _mark_running(self) -> None:
        if not self._staging:
            super()._mark_running()

    def _previous_folders(self, folder: Path) -> set[str]:
        """The results folders of the previous result in ``folder`` (listed in its MANIFEST, or known names)."""
        listed = _manifest_entries(folder)[1] if self.listing else set()
        return {name for name in set(self.owned_folders) | set(self.result_folders) | listed
                if (folder / name).is_dir()}

    def subfolder(self, name: str) -> ResultsFolder:
        sub = super().subfolder(name)
        self._subs.append(sub)
        return sub

    def published(self, path: str | os.PathLike) -> Path:
        """The name ``path`` (inside the staging folder, or anywhere) has once the run is published."""
        path = Path(path)
        stage = getattr(self, "_stage", None) or (self.path if self._publication is not None else None)
        if stage is not None and (path == stage or stage in path.parents):
            return self.final_path / path.relative_to(stage)
        return path

    def complete(self) -> None:
        if not self._staging:
            super().complete()
            self._completed = True
            return
        stage, final = self.path, self.final_path
        self._stage = stage
        for sub in self._subs:            # the method folders' locks and file lists, before they are moved
            sub.release()
        with contextlib.suppress(FileNotFoundError):
            (stage / RUNNING_MARKER).unlink()
        entries = [e for e in os.scandir(stage) if TEMP_TAG not in e.name and e.name != LOCK_NAME]
        published = {e.name for e in entries}
        if self.listing:
            record = {"files": sorted(e.name for e in entries if e.is_file(follow_symlinks=False))}
            if self.folders:
                record["folders"] = sorted(self.folders)
            atomic_write_json(stage / MANIFEST, record)
            published.add(MANIFEST)
        self._retire_previous(stage, final, published)
        publication, self._publication, self._set = self._publication, None, None
        publication.__exit__(None, None, None)        # the commit: the new result replaces the previous one
        self.path = final
        self._completed = True
        # the folder's MANIFEST (rewritten on release) lists the published files and those written since, not the
        # user's files beside them
        self._before = {name: ident for name, ident in self._inodes().items() if name not in published}

    def _retire_previous(self, stage: Path, final: Path, published: set[str]) -> None:
        """Plan the previous result's removal in the commit: its files and folders the new one does not replace,
        the user's files in its results folders carried into the new ones."""
        files = _manifest_entries(final)[0] if self.listing else set()
        files |= {n for n in self.result_names if not _is_pattern(n)}
        files |= {m.name for n in self.result_names if _is_pattern(n) for m in final.glob(n)}
        for name in sorted(files - published - {LOCK_NAME}):
            path = final / name
            if path.is_symlink() or path.is_file():
                self._set.retire(path)
        owned = set(self.owned_folders)
        for name in sorted(self._previous_folders(final)):
            path = final / name
            if path.is_symlink():
                continue
            keep = [] if name in owned else _foreign_entries(path)
            for entry in keep:
                target = stage / name / entry
                if not os.path.lexists(target):
                    (stage / name).mkdir(exist_ok=True)
                    _link_tree(path / entry, target)
            if name not in published and not keep:
                self._set.retire(path)
            elif keep:
                log.info("%s: the files not its own are kept in the new %s", path, name)

    def release(self) -> None:
        if self._publication is not None:   # not completed: the staged run goes, the previous result stands
            publication, self._publication, self._set = self._publication, None, None
            with contextlib.suppress(RuntimeError):
                publication.__exit__(RuntimeError, RuntimeError("run not completed"), None)
            self.path = self.final_path
        if self._staging and not self._completed:
            self.lock.release()             # the previous run's file list stays: its files are the ones in place
            return
        super().release()


def _foreign_entries(folder: Path) -> list[str]:
    """The entries of a previous results folder that are not results (the user's notes, say)."""
    listed = _manifest_entries(folder)[0]
    try:
        names = [e.name for e in os.scandir(folder)]
    except OSError:
        return []
    return sorted(n for n in names if n not in RESULT_NAMES and n not in listed and n != LOCK_NAME
                  and TEMP_TAG not in n)


def _link_tree(source: Path, target: Path) -> None:
    """``target`` holding what ``source`` holds: hard links (copies where the file system has none)."""
    if source.is_symlink():
        os.symlink(os.readlink(source), target)
    elif source.is_dir():
        target.mkdir()
        for entry in os.scandir(source):
            _link_tree(Path(entry.path), target / entry.name)
    else:
        try:
            os.link(source, target)
        except OSError:
            shutil.copy2(source, target)


class ReconstructionFolder(StagedResultsFolder):
    """The results folder of ``radiomap reconstruct``: with ``force`` over a COMPLETE previous run, that run stays in
    place until the new one is complete and published as one set (``metrics.json`` last; module doc). A first run,
    or one over an incomplete folder, is written in place (``RUNNING`` marker, ``"status": "running"``)."""

    primary = "metrics.json"
