"""The command group: version, help with examples, unknown commands, one-line errors."""

from __future__ import annotations

import subprocess
import sys

import pytest

from radiometry import __version__


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mapping.cli", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.slow
def test_version():
    out = run("--version")
    assert out.returncode == 0
    lines = out.stdout.strip().splitlines()
    assert lines[0] == f"radiomap {__version__}" and lines[1].startswith("kernels: ")
    assert run("-V").stdout == out.stdout


@pytest.mark.slow
def test_version_says_which_kernels_run(monkeypatch):
    monkeypatch.setenv("RADIOMAP_KERNELS", "numba")
    assert run("--version").stdout.strip().splitlines()[1] == "kernels: Numba (RADIOMAP_KERNELS=numba)"
    monkeypatch.setenv("RADIOMAP_KERNELS", "fortran")
    out = run("--version")
    assert out.returncode == 0 and "kernels: none usable: RADIOMAP_KERNELS='fortran'" in out.stdout


def test_help_lists_examples():
    out = run("--help")
    assert out.returncode == 0
    assert "Examples:" in out.stdout and "radiomap response" in out.stdout


def test_unknown_command_fails_and_lists_the_commands():
    out = run("no-such-command")
    assert out.returncode != 0
    assert "No such command 'no-such-command'; choose one of demo, response, simulate, vignetting, correct, " \
           "reconstruct, compare" in out.stderr


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


def _visible_options():
    """{option spelling: [(command, parameter)]} over every subcommand's --help."""
    import click

    from mapping.cli import SUBCOMMANDS

    seen = {}
    for name, command in SUBCOMMANDS.items():
        for param in command.params:
            if isinstance(param, click.Option) and not param.hidden:
                for spelling in param.opts + param.secondary_opts:
                    seen.setdefault(spelling, []).append((name, param))
    return seen


def test_one_meaning_per_option_name_across_the_cli():
    """-v is only the top level's --verbose; an option spelled alike in several subcommands has one kind of value
    (a range, a model file, a layout...): --frames is always A:B:S, --vignetting always a model file."""
    from mapping.cli import cli
    from mapping.cli._common import FrameRange

    import click

    seen = _visible_options()
    assert "-v" not in seen and "-v" in next(p for p in cli.params if p.name == "verbose").opts
    for spelling, uses in seen.items():
        kinds = {(type(p.type).__name__, p.is_flag, p.count) for _, p in uses}
        assert len(kinds) == 1, (spelling, [(c, p.name, p.type) for c, p in uses])
    assert all(isinstance(p.type, FrameRange) for _, p in seen["--frames"])
    assert all(isinstance(p.type, click.Path) for _, p in seen["--vignetting"])
    assert all("tum" in p.type.choices for _, p in seen["--format"])
    assert [c for c, _ in seen["--num-frames"]] == ["simulate"] and "-n" in seen


@pytest.mark.slow
def test_renamed_options_are_hidden_aliases():
    from click.testing import CliRunner

    from mapping.cli import cli

    for command, old in (("reconstruct", "--reference-exposure"), ("reconstruct", "--exposure-reference"),
                         ("reconstruct", "-v,"), ("correct", "-v,"), ("correct", "--format"),
                         ("simulate", "--frames"), ("simulate", "--exposure "), ("simulate", "--vignetting ")):
        out = CliRunner().invoke(cli, [command, "--help"]).output
        assert old not in out, (command, old)


@pytest.mark.slow
def test_the_defaults_that_differ_are_the_ones_the_summaries_name():
    """reconstruct and compare keep different defaults only for poses and exposure compensation (GLB is on in
    both); the table the summaries quote matches the options."""
    import importlib

    from mapping.cli._common import DIFFERENT_DEFAULTS

    import click

    def default(command, name):
        cmd = importlib.import_module(f"mapping.cli.{command}").command
        return next(p.get_default(click.Context(cmd)) for p in cmd.params if p.name == name)

    assert default("reconstruct", "poses") == DIFFERENT_DEFAULTS["poses"]["reconstruct"] == "icp"
    assert default("compare", "poses") == DIFFERENT_DEFAULTS["poses"]["compare"] == "gt"
    assert default("reconstruct", "exposure_compensation") is None     # on with --response
    assert default("compare", "exposure_compensation") is False and \
        DIFFERENT_DEFAULTS["exposure_compensation"]["compare"] == "off"
    assert default("compare", "formats") == default("reconstruct", "formats") == "ply"   # one mesh, the PLY
    shared = {"backend", "voxel_size", "depth_max", "frames", "depth_scale", "intrinsics", "format"}
    assert all(default("reconstruct", n) == default("compare", n) for n in shared)


def test_simulate_num_frames_and_its_old_spelling(tmp_path):
    from click.testing import CliRunner

    from mapping.cli import cli

    tiny = ["--width", "32", "--height", "24", "--no-progress"]
    res = CliRunner().invoke(cli, ["simulate", "brackets", "-o", str(tmp_path / "a"), "-n", "3", *tiny])
    assert res.exit_code == 0, res.output
    assert len((tmp_path / "a" / "times.txt").read_text().splitlines()) == 3
    res = CliRunner().invoke(cli, ["simulate", "brackets", "-o", str(tmp_path / "b"), "--frames", "2", *tiny])
    assert res.exit_code == 0, res.output
    assert "warning: --frames is deprecated, use --num-frames (a count here; --frames is a range A:B:S" in res.stderr
    assert len((tmp_path / "b" / "times.txt").read_text().splitlines()) == 2


@pytest.mark.parametrize("field, option", [("reference_exposure", "--display-exposure"),
                                           ("exposure_reference", "--mesh-exposure"),
                                           ("voxel_size", "--voxel-size")])
def test_range_errors_name_the_option_the_user_typed(field, option):
    """A config field whose option was renamed is named by the option's current spelling in range errors."""
    from mapping.validation import check_exposure_factor

    with pytest.raises(ValueError) as exc:
        check_exposure_factor(float("inf"), field)
    assert str(exc.value).startswith(f"{option} inf is not a finite number")
    with pytest.raises(ValueError) as exc:
        check_exposure_factor(1e9, field)
    assert str(exc.value).startswith(f"{option} 1e+09 is outside")
