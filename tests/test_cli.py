"""The command group: version, help with examples, unknown commands, one-line errors."""

from __future__ import annotations

import subprocess
import sys

import pytest

from radiometry import __version__


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mapping.cli", *args], capture_output=True, text=True, timeout=120)


def test_version():
    out = run("--version")
    assert out.returncode == 0
    assert out.stdout.strip() == f"radiomap {__version__}"


def test_help_lists_examples():
    out = run("--help")
    assert out.returncode == 0
    assert "Examples:" in out.stdout and "radiomap response" in out.stdout


def test_unknown_command_fails():
    out = run("no-such-command")
    assert out.returncode != 0
    assert "No such command" in out.stderr


def test_known_error_is_one_line_without_traceback(tmp_path):
    import click

    from mapping.cli import SUBCOMMANDS, cli
    from radiometry.errors import CalibrationFileError

    @click.command()
    def failing():
        raise CalibrationFileError("crf.npz: not a radiomap response file; re-create it")

    cli.add_command(failing, "failing-test")
    try:
        from click.testing import CliRunner

        result = CliRunner().invoke(cli, ["failing-test"])
    finally:
        cli.commands.pop("failing-test", None)
    assert result.exit_code == 1
    assert result.output.strip().splitlines() == [
        "radiomap: error: crf.npz: not a radiomap response file; re-create it"]
    assert "Traceback" not in result.output
    assert "failing-test" not in SUBCOMMANDS


@pytest.mark.parametrize("name", ["response", "simulate", "vignetting", "correct", "reconstruct"])
def test_subcommand_help(name):
    from mapping.cli import SUBCOMMANDS

    import importlib.util

    if importlib.util.find_spec(SUBCOMMANDS[name]) is None:
        pytest.skip(f"subcommand {name} not built yet")
    out = run(name, "--help")
    assert out.returncode == 0, out.stderr
    assert "Usage:" in out.stdout


def _invoke_failing(fn):
    import click
    from click.testing import CliRunner

    from mapping.cli import cli

    cli.add_command(click.command()(fn), "failing-test")
    try:
        return CliRunner().invoke(cli, ["failing-test"])
    finally:
        cli.commands.pop("failing-test", None)


def test_open3d_error_is_one_line_without_colour_codes():
    """An error from Open3D's C++ core (here a real one: ICP without a single correspondence) prints its message
    on one line, without the terminal colour codes, the C++ signature and the source path; exit 1."""
    import numpy as np

    from mapping._open3d import o3d

    def failing():
        nan = o3d.core.Tensor(np.full((8, 8, 3), np.nan, np.float32))
        o3d.t.pipelines.odometry.compute_odometry_result_point_to_plane(
            nan, nan, nan, o3d.core.Tensor(np.eye(3)), o3d.core.Tensor(np.eye(4)), 0.07, 0.05)

    result = _invoke_failing(failing)
    assert result.exit_code == 1
    assert result.output.strip().splitlines() == [
        "radiomap: error: Open3D failed: Singular 6x6 linear system detected, tracking failed. (check the input "
        "and the options; -vv logs the details)"]


def test_out_of_memory_is_one_line():
    def failing():
        raise MemoryError

    result = _invoke_failing(failing)
    assert result.exit_code == 1 and len(result.output.strip().splitlines()) == 1
    assert "out of memory" in result.output and "--voxel-size" in result.output


def test_other_runtime_errors_are_bugs_and_keep_their_traceback():
    def failing():
        raise RuntimeError("a bug")

    result = _invoke_failing(failing)
    assert result.exit_code == 1 and isinstance(result.exception, RuntimeError)
