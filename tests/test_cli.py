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
