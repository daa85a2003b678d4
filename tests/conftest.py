"""Shared fixtures: the real camera data beside the checkout, temporary outputs."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("RADIOMAP_SHARED_DATA", REPO.parent / "shared" / "data"))

# radiomap's cache (the sample sequences, mapping/simulation/samples.py) in the temporary folder, not in the user's
# home: set before any test runs, so that the commands the tests start inherit it. Kept between sessions (a sample is
# rebuilt only when its recipe or radiomap's version changes); per user, as /tmp is shared.
TEST_CACHE = Path(os.environ.setdefault("RADIOMAP_CACHE_DIR", str(Path(tempfile.gettempdir()) /
                                                                   f"radiomap-test-cache-{os.getuid()}")))


def shared_path(*parts: str) -> Path:
    """A path under ../shared/data; skips the calling test with a reason when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real camera data {path} is absent (it lives in ../shared/data beside the checkout)")
    return path


def build_without_simd(tmp_path: Path, package: str) -> Path:
    """Build radiomap's C extensions with ``-DRM_NO_SIMD`` (what other compilers and CPUs build) under ``tmp_path``
    and return the built ``<package>._ckernels`` file; skips the calling test without a C compiler."""
    import shutil
    import subprocess
    import sys
    import sysconfig

    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(cc) is None or sys.platform == "win32":
        pytest.skip(f"no C compiler ({cc})")
    env = dict(os.environ, CFLAGS="-DRM_NO_SIMD")
    proc = subprocess.run([sys.executable, "setup.py", "build_ext", "--build-lib", str(tmp_path / "lib"),
                           "--build-temp", str(tmp_path / "tmp")], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return next((tmp_path / "lib" / package).glob("_ckernels*"))


@pytest.fixture
def shared_data() -> Path:
    return shared_path()


def run_paused(script: str, argv: list, sig: int, *, env: dict | None = None):
    """Run ``python -c script FD ARGV...`` where ``script`` writes ``paused`` to the pipe FD once it has stopped at the
    moment under test, then send it ``sig`` and wait for it: a child interrupted at an event, never after a sleep
    that races it. Returns a ``subprocess.CompletedProcess`` with its output."""
    import os
    import select
    import subprocess
    import sys

    read_end, write_end = os.pipe()
    proc = subprocess.Popen([sys.executable, "-c", script, str(write_end), *map(str, argv)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[1], env=env,
                            pass_fds=(write_end,))
    os.close(write_end)
    try:
        ready, _, _ = select.select([read_end], [], [], 600)   # ends a hung test only; the pause comes in seconds
        assert (os.read(read_end, 16) if ready else b"") == b"paused", ("the run ended before", argv[:1], proc.poll())
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=600)
        return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    finally:
        os.close(read_end)
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.fixture(scope="session")
def selfcal_room(tmp_path_factory):
    """A small simulated room that constrains self-calibration (160x120, 30 frames, the 'asymmetric' camera, seed 1),
    made once per test session for the self-calibration tests."""
    from mapping.simulation.sequences import simulate_room
    from mapping.simulation.trajectory import HandheldMotion
    from radiometry.simulation.camera import CameraSpec

    out = tmp_path_factory.mktemp("selfcal") / "room"
    simulate_room(out, camera=CameraSpec.preset("asymmetric", width=160, height=120), seed=1, n_frames=30,
                  width=160, height=120, motion=HandheldMotion(speed=3.0), progress=False)
    return out
