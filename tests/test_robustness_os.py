"""Operating-system errors, structural JSON failures, zombie lock owners, Ctrl-C consequences and long error lines
(issue 31): each a one-line error naming the path (or "radiomap: interrupted", exit 130), never a traceback."""

from __future__ import annotations

import errno
import json
import os
import select
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from test_robustness import BRACKETS, REPO, brackets, error_line, run  # noqa: F401 (fixture)

from mapping.export import FolderLock, _process_start
from radiometry.errors import shorten
from radiometry.fileio import pid_alive


# --------------------------------------------------------------------------------------------------
# operating-system limits
# --------------------------------------------------------------------------------------------------
def test_a_path_too_long_is_one_line(tmp_path):
    out = tmp_path / ("a" * 300 + ".npz")
    line = error_line(run("response", "--gamma", "2.2", "-o", out), "too long")
    assert "aaaa" in line and len(line) < 600          # names the path, cut to a readable length
    folder = tmp_path / ("b" * 300)
    error_line(run("simulate", "paper", "-n", "2", "--width", "32", "--height", "24", "-o", folder), "too long")


@pytest.mark.parametrize("code, fragment", [(errno.EMFILE, "too many open files"),
                                            (errno.EROFS, "read-only"),
                                            (errno.EACCES, "permission denied"),
                                            (errno.ENAMETOOLONG, "too long")])
def test_os_errors_while_writing_name_the_file(tmp_path, monkeypatch, code, fragment):
    import radiometry.fileio as fileio

    def fail(*args, **kwargs):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(fileio.tempfile, "mkstemp", fail)
    monkeypatch.setattr(fileio.tempfile, "mkdtemp", fail)
    out = tmp_path / "r.npz"
    error_line(run("response", "--gamma", "2.2", "-o", out), fragment, "r.npz")
    assert not out.exists()


def test_an_os_error_no_reader_expected_is_one_line(tmp_path, monkeypatch):
    """An OSError raised where no reader turns it into a RadiomapError (here: listing the bracket folder) is still
    one line naming the path, by the CLI's last resort."""
    monkeypatch.setattr(Path, "iterdir", lambda self: (_ for _ in ()).throw(
        OSError(errno.EMFILE, os.strerror(errno.EMFILE), str(self))))
    error_line(run("response", BRACKETS, "-o", tmp_path / "r.npz"), "Too many open files", str(BRACKETS),
               "ulimit -n")


# --------------------------------------------------------------------------------------------------
# config files Python's JSON reader cannot parse for structural reasons
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("text, fragment", [
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ('{"config_version": 1, "command": "reconstruct", "parameters": {"voxel_size": ' + "9" * 5000 + "}}",
     "not a JSON file radiomap can read"),
    ('{"a": "' + "x" * 1_000_000, "not a JSON file"),
])
def test_a_config_json_that_cannot_be_parsed_is_one_line(tmp_path, text, fragment):
    config = tmp_path / "config.json"
    config.write_text(text)
    line = error_line(run("reconstruct", "--config", config, "-o", tmp_path / "out"), str(config), fragment)
    assert len(line) < 1000
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------------
# a lock held by a zombie
# --------------------------------------------------------------------------------------------------
def _zombie() -> subprocess.Popen:
    """A child that has exited and is not reaped (its parent, this test, has not waited for it)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    fd = os.pidfd_open(proc.pid) if hasattr(os, "pidfd_open") else None
    if fd is not None:
        select.select([fd], [], [], 60)     # readable once the child has exited (it stays unreaped)
        os.close(fd)
    else:  # pragma: no cover (Linux < 5.3)
        while Path(f"/proc/{proc.pid}/status").read_text().split("State:")[1].split()[0] != "Z":
            os.sched_yield()
    return proc


@pytest.mark.slow
def test_a_lock_held_by_a_zombie_is_stale(tmp_path, caplog):
    import socket

    proc = _zombie()
    try:
        status = Path(f"/proc/{proc.pid}/status").read_text()
        assert "State:\tZ" in status
        assert not pid_alive(proc.pid)
        folder = tmp_path / "out"
        folder.mkdir()
        (folder / "LOCK").write_text(json.dumps({"pid": proc.pid, "start": _process_start(proc.pid),
                                                 "host": socket.gethostname(), "what": "run"}))
        with caplog.at_level("WARNING"), FolderLock(folder):
            assert json.loads((folder / "LOCK").read_text())["pid"] == os.getpid()
        assert "which no longer runs" in caplog.text
    finally:
        proc.wait()


@pytest.mark.slow
def test_a_live_owner_still_holds_its_lock(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    try:
        folder = tmp_path / "out"
        with FolderLock(folder):
            pass
        import socket

        (folder / "LOCK").write_text(json.dumps({"pid": proc.pid, "start": _process_start(proc.pid),
                                                 "host": socket.gethostname(), "what": "run"}))
        assert pid_alive(proc.pid)
        with pytest.raises(Exception, match="in use by another radiomap run"):
            FolderLock(folder)
    finally:
        proc.communicate(b"")


# --------------------------------------------------------------------------------------------------
# Ctrl-C at any moment: one line
# --------------------------------------------------------------------------------------------------
_IMPORT_CUT = r"""
import os, sys, time
ready = int(sys.argv[1])
import radiometry.plots as plots

def figure(*args, **kwargs):   # stands for a lazy import that Ctrl-C cuts half-way and that then fails
    try:
        os.write(ready, b"paused"); os.close(ready)
        while True:
            time.sleep(0.05)
    except KeyboardInterrupt:
        raise ImportError("cannot import name 'pyplot' from partially initialized module 'matplotlib'")

plots.response_figure = figure
from mapping.cli import main
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("sig, code, line", [(signal.SIGINT, 130, "radiomap: interrupted"),
                                             (signal.SIGTERM, 143, "radiomap: terminated (SIGTERM)")],
                         ids=["SIGINT", "SIGTERM"])
def test_an_error_caused_by_ctrl_c_is_reported_as_the_interruption(tmp_path, sig, code, line):
    read_end, write_end = os.pipe()
    proc = subprocess.Popen([sys.executable, "-c", _IMPORT_CUT, str(write_end), "response", "--gamma", "2.2", "-o",
                             str(tmp_path / "r.npz")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=REPO, pass_fds=(write_end,), preexec_fn=lambda: signal.signal(signal.SIGINT,
                                                                                               signal.SIG_DFL))
    os.close(write_end)
    try:
        ready, _, _ = select.select([read_end], [], [], 300)
        assert ready and os.read(read_end, 16) == b"paused"
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=300)
    finally:
        os.close(read_end)
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == code and err.strip().splitlines()[-1] == line, err
    assert "Traceback" not in err and not (tmp_path / "r.npz").exists()


# --------------------------------------------------------------------------------------------------
# error lines cut what they quote
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_huge_token_of_a_broken_list_is_cut(brackets, tmp_path):  # noqa: F811
    lines = (brackets / "times.txt").read_text().splitlines()
    lines[-1] = lines[-1].split()[0] + " " + "9x" * 3_000_000           # a 6 MB "time"
    (brackets / "times.txt").write_text("\n".join(lines) + "\n")
    line = error_line(run("response", brackets, "-o", tmp_path / "r.npz"), "times.txt", "characters")
    assert len(line) < 2100


@pytest.mark.slow
def test_shorten_keeps_short_lines_and_cuts_long_tokens():
    assert shorten("a short line; fix it") == "a short line; fix it"
    cut = shorten("x: " + "y" * 10_000 + " fix")
    assert cut.startswith("x: yyy") and cut.endswith(" fix") and "(10,000 characters)" in cut and len(cut) < 300
    assert "\n" not in shorten("two\nlines")
