"""Every float option of every command refuses inf, -inf and nan (issue 31): one line, exit 1, nothing written.

The test walks the commands' options themselves (``SUBCOMMANDS``), so an option added later with click's plain
``float`` (which, like ``FloatRange``, lets ``nan`` through: every comparison with it is false) fails here until
it uses :class:`mapping.cli._common.Number`, the one option type that applies ``mapping/validation.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import click
import pytest
from test_robustness import error_line, run, snapshot

from mapping.cli import SUBCOMMANDS
from mapping.cli._common import Number

#: the least each command needs besides the option under test ({IN}: an existing folder, {FILE}: an existing file,
#: {OUT}: a path under the output folder, which must not exist afterwards)
BASE = {
    "response": ["-o", "{OUT}/r.npz"],
    "simulate": ["paper", "-o", "{OUT}/sim"],
    "vignetting": ["{IN}", "-r", "{FILE}", "-o", "{OUT}/v.npz"],
    "correct": ["{IN}", "-r", "{FILE}", "--vignetting", "{FILE}", "-o", "{OUT}/c"],
    "reconstruct": ["{IN}", "-o", "{OUT}/rec"],
    "compare": ["{IN}", "-r", "{FILE}", "-o", "{OUT}/cmp"],
    "self-calibrate": ["{IN}", "-o", "{OUT}/sc"],
}


def float_options() -> list[tuple[str, str]]:
    """(command, option) of every option whose values are floats, in every subcommand."""
    found = []
    for name in SUBCOMMANDS:
        for param in SUBCOMMANDS[name].params:
            if isinstance(param, click.Option) and not param.hidden and \
                    isinstance(param.type, (click.types.FloatParamType, Number)):
                found.append((name, max(param.opts, key=len)))
    return found


@pytest.mark.slow
def test_every_float_option_is_a_checked_number():
    """Plain ``float`` / ``FloatRange`` options let nan through: every float option is a Number."""
    found = float_options()
    assert len(found) >= 15, found          # the walk finds them (voxel sizes, depth ranges, gamma, flicker, ...)
    plain = [(c, o) for c, o in found if not isinstance(_param(c, o).type, Number)]
    assert not plain, f"float options without the finite/range check of mapping.validation: {plain}"
    for command in {c for c, _ in found}:
        assert command in BASE, f"add the least arguments of {command!r} to BASE"


def _param(command: str, option: str) -> click.Option:
    return next(p for p in SUBCOMMANDS[command].params if isinstance(p, click.Option) and option in p.opts)


@pytest.fixture(scope="module")
def places(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("options")
    (root / "in").mkdir()
    (root / "in" / "notes.txt").write_text("an input that must stay as it is\n")
    (root / "file.npz").write_bytes(b"not read: the option is refused first")
    return {"IN": root / "in", "FILE": root / "file.npz", "root": root}


@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "NaN", "1e999"])
@pytest.mark.parametrize("command, option", float_options())
def test_non_finite_values_are_one_line_and_write_nothing(places, tmp_path, command, option, value):
    out = tmp_path / "out"
    args = [a.format(IN=places["IN"], FILE=places["FILE"], OUT=out) for a in BASE[command]]
    before = snapshot(places["root"])
    line = error_line(run(command, *args, f"{option}={value}"), option, "not a finite number")
    assert "sensible range" in line or "finite" in line
    assert not out.exists(), f"{command} {option} {value} wrote {sorted(out.rglob('*'))}"
    assert snapshot(places["root"]) == before


@pytest.mark.slow
@pytest.mark.parametrize("command, option, value, fragments", [
    ("response", "--gamma", "0.1", ["--gamma 0.1", "0.2..5"]),
    ("simulate", "--flicker", "0.5", ["--flicker 0.5", "0.5 excluded"]),
    ("reconstruct", "--display-exposure", "0", ["--display-exposure 0", "0.0001..10000"]),
    ("compare", "--depth-scale", "-5", ["--depth-scale -5", "1..100000"]),
    ("self-calibrate", "--depth-scale", "0", ["--depth-scale 0", "1..100000"]),
    ("response", "--lambda", "-1", ["--lambda -1", "1e-06..1e+06"]),     # were usage errors of FloatRange
    ("response", "--lambda", "0", ["--lambda 0", "1e-06..1e+06"]),
])
def test_out_of_range_values_name_the_option_and_the_range(places, tmp_path, command, option, value, fragments):
    out = tmp_path / "out"
    args = [a.format(IN=places["IN"], FILE=places["FILE"], OUT=out) for a in BASE[command]]
    error_line(run(command, *args, option, value), *fragments)
    assert not out.exists()


def test_a_non_number_is_a_usage_error_that_quotes_a_readable_length(places, tmp_path):
    res = run("reconstruct", places["IN"], "-o", tmp_path / "o", "--voxel-size", "x" * 100_000)
    assert res.exit_code == 2 and "is not a valid float" in res.output and len(res.output) < 2000


def test_a_replayed_config_with_infinity_names_the_key(places, tmp_path):
    """config.json may hold Infinity/NaN (Python's JSON reads them): the key is named, nothing is written."""
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"command": "reconstruct", "config_version": 1,
                                  "parameters": {"sequence": str(places["IN"]), "voxel_size": float("inf")}}))
    out = tmp_path / "out"
    error_line(run("reconstruct", "--config", config, "-o", out), "parameters.voxel_size", "not a finite number")
    assert not out.exists()


@pytest.mark.slow
def test_batch_passes_the_same_check(places, tmp_path):
    listing = tmp_path / "list.txt"
    listing.write_text(f"{places['IN']}\n")
    out = tmp_path / "out"
    error_line(run("batch", "reconstruct", listing, "-o", out, "--", "--depth-max", "nan"), "--depth-max",
               "not a finite number")
    assert not out.exists()
