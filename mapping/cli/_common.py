"""Shared pieces of the subcommands: option types, deprecated option spellings, run manifests and their
replay (``--config RUN/config.json``), summary tables.

Option naming (one meaning per name and per short option across the whole CLI): ``-o`` output, ``-r``
response, ``-v`` only ``radiomap -v`` (verbose), ``-n`` a count of frames; ``--frames`` is always a range
``A:B:S``; ``--vignetting`` always a model file; ``--format`` always a sequence layout. A renamed option keeps
its old spelling as a hidden alias (:func:`deprecated_alias`) that warns in one line.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource

from mapping.datasets import FORMATS
from mapping.factory import BACKENDS
from mapping.export import plain_value
from mapping.validation import DEPTH_MAX_M, DEPTH_SCALE, POSE_TIME_DIFFERENCE_S, ImplausibleValueError, VOXEL_SIZE_M
from radiometry import __version__
from radiometry.errors import RadiomapError, shorten

# the version of config.json's replay contract ("parameters" = the command's options by their Python names)
CONFIG_VERSION = 1
# options that never come from a config.json: what to overwrite and how to show progress are the caller's
NOT_REPLAYED = frozenset({"config", "force", "no_progress", "progress", "help"})
# keys of config.json besides "parameters": what the run was and where it ran (read by people, not replayed)
CONFIG_INFO_KEYS = ("command", "config_version", "parameters", "argv", "replay_of", "radiomap_version", "python",
                    "platform", "started", "dataset", "colour_model", "pipeline", "methods_run", "inputs")
_META_CONFIG = "radiomap.config"
_META_RECORD = "radiomap.config_record"     # the replayed config.json's document (its inputs and dataset)
_META_ARGV = "radiomap.argv"
_META_ALIAS_VALUES = "radiomap.alias_values"


class ConfigFileError(RadiomapError):
    """A ``--config`` file cannot be replayed (not JSON, another command or version, an unknown key)."""


class Number(click.ParamType):
    """A float option checked by :mod:`mapping.validation` as it is parsed: finite (``inf``, ``-inf`` and ``nan``
    are refused, which click's ``float`` and ``FloatRange`` let through) and, with ``limits``, within the sensible
    range (:func:`mapping.validation.check_range`; ``open_max`` excludes the upper limit). Every float option of
    every command is of this type (``tests/test_robustness_options.py`` walks them all). A refusal is one line
    (``radiomap: error: --voxel-size inf is not a finite number; ...``, exit 1), before anything is read or
    written."""

    name = "FLOAT"

    def __init__(self, limits: tuple[float, float] | None = None, unit: str = "", why: str = "", *,
                 open_max: bool = False) -> None:
        self.limits, self.unit, self.why, self.open_max = limits, unit, why, open_max

    def convert(self, value, param, ctx):
        from mapping.validation import check_finite, check_range, quote

        label = max(param.opts, key=len) if isinstance(param, click.Option) else (param.name if param else "value")
        if isinstance(value, str):
            try:
                value = float(value.strip())
            except ValueError:
                self.fail(f"{quote(value)} is not a valid float", param, ctx)
        if self.limits is None:
            return check_finite(label, value)
        return check_range(label, value, self.limits, self.unit, self.why, open_max=self.open_max)


class FrameRange(click.ParamType):
    """``A:B:S`` (Python slice syntax, each part optional) -> ``slice``."""

    name = "A:B:S"

    def convert(self, value, param, ctx):
        if isinstance(value, slice):
            return value
        parts = str(value).split(":")
        if len(parts) > 3:
            self.fail(f"{_quote(value)} is not A:B:S (e.g. 0:100:2)", param, ctx)
        try:
            nums = [int(p) if p.strip() else None for p in parts]
        except ValueError:
            self.fail(f"{_quote(value)} is not A:B:S with whole numbers (e.g. 0:100:2)", param, ctx)
        while len(nums) < 3:
            nums.append(None)
        if len(parts) == 1 and nums[0] is not None:  # a single number N means the first N frames
            if nums[0] < 0:
                self.fail(f"{_quote(value)}: the number of frames must be >= 0 (N: the first N frames)", param, ctx)
            nums = [0, nums[0], None]
        if nums[0] is not None and nums[0] < 0:
            self.fail(f"the start in {_quote(value)} must be a frame index >= 0 (A:B:S counts from the first frame, "
                      "0)", param, ctx)
        if nums[2] is not None and nums[2] <= 0:
            self.fail(f"the step in {_quote(value)} must be positive", param, ctx)
        return slice(*nums)


def _quote(value) -> str:
    from mapping.validation import quote

    return quote(value)


def run_manifest(command: str, params: dict[str, Any]) -> dict[str, Any]:
    """What a results folder records about the run that made it."""
    return {
        "command": command,
        "argv": sys.argv,
        "parameters": {k: plain_value(v) for k, v in params.items()},
        "radiomap_version": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def replay_manifest(ctx: click.Context, *, files: tuple[str, ...] = (), inputs: tuple[str, ...] = (),
                    **info: Any) -> dict[str, Any]:
    """config.json of a replayable command: its options as plain values under "parameters" (``--config``
    reads them back), ``info`` (keys of :data:`CONFIG_INFO_KEYS`) beside them. ``files``: text options that
    may name a file (e.g. ``--intrinsics``), recorded absolute when they do. ``inputs``: the options whose file the
    run reads, recorded under "inputs" with their sha256 and size (:mod:`mapping.replay`); a replay refuses when a
    file it takes from its config.json differs from the recorded one (:func:`check_replayed_inputs`)."""
    from mapping.replay import INPUTS_KEY, input_records

    records = input_records({p.name: ctx.params.get(p.name) for p in ctx.command.params if p.name in inputs and
                             not (isinstance(p.type, PoseSource) and isinstance(ctx.params.get(p.name), str))})
    check_replayed_inputs(ctx, records, inputs)
    params = {}
    for param in ctx.command.params:
        if not _replayable(param) or param.name not in ctx.params:
            continue
        value = ctx.params[param.name]
        if param.name in files and isinstance(value, str) and Path(value).is_file():
            value = Path(value)
        if isinstance(value, list) and not getattr(param, "multiple", False):
            value = ",".join(map(str, value))        # a comma-separated option the callback split
        params[param.name] = plain_value(value)
    unknown = set(info) - set(CONFIG_INFO_KEYS)
    if unknown:
        raise ValueError(f"config.json info keys must be among CONFIG_INFO_KEYS, got {sorted(unknown)}")
    manifest = {"command": ctx.command.name, "config_version": CONFIG_VERSION, "parameters": params,
                "argv": ctx.meta.get(_META_ARGV, sys.argv)}
    if ctx.meta.get(_META_CONFIG) is not None:
        manifest["replay_of"] = os.path.abspath(ctx.meta[_META_CONFIG])
    manifest.update({"radiomap_version": __version__, "python": sys.version.split()[0],
                     "platform": platform.platform(), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
    manifest.update(info)
    manifest[INPUTS_KEY] = records
    return manifest


def check_replayed_inputs(ctx: click.Context, records: dict[str, Any], inputs: tuple[str, ...]) -> None:
    """With ``--config``: the files of ``inputs`` taken from the config.json compared with those it recorded
    (:func:`mapping.replay.check_inputs`; an option given on the command line replaces the recorded file and is not
    compared); a config.json that recorded none gets a one-line note on stderr."""
    config, doc = ctx.meta.get(_META_CONFIG), ctx.meta.get(_META_RECORD)
    if config is None or doc is None:
        return
    from mapping.replay import INPUTS_KEY, check_inputs, unchecked_note

    note = unchecked_note(config, doc)
    if note is not None:
        click.echo(note, err=True)
        return
    recorded = doc[INPUTS_KEY] if isinstance(doc[INPUTS_KEY], dict) else {}
    spellings = {p.name: max(p.opts, key=len) for p in ctx.command.params   # used, and taken from the file
                 if p.name in inputs and ctx.params.get(p.name) is not None and
                 ctx.get_parameter_source(p.name) is ParameterSource.DEFAULT_MAP}
    check_inputs(config, recorded, records, spellings)


def replayed_sequence(ctx: click.Context) -> dict[str, Any] | None:
    """With ``--config``, when SEQUENCE, --frames and --format all come from the config.json: what its run recorded
    of the frames (``frames``, ``frame_names_sha256``, ``ground_truth_sha256``, K and depth scale unless given) for
    :func:`mapping.replay.check_frames`, which the command calls once the sequence is open; else None."""
    config, doc = ctx.meta.get(_META_CONFIG), ctx.meta.get(_META_RECORD)
    if config is None or doc is None or not isinstance(doc.get("dataset"), dict):
        return None
    if ctx.get_parameter_source("sequence") is not ParameterSource.DEFAULT_MAP or \
            any(ctx.get_parameter_source(n) in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT)
                for n in ("frames", "format")):
        return None
    dataset = doc["dataset"]
    from mapping.replay import selection_record

    # what selected the recorded frames (an older file: its pipeline's options); another selection (a hand-edited
    # parameters.frames) is not compared
    recorded = dataset.get("selected_with") or doc.get("pipeline")
    if not isinstance(recorded, dict):
        return None
    now = selection_record(ctx.params["sequence"], ctx.params.get("frames"), ctx.params.get("format"))
    if any(recorded.get(k) != v for k, v in now.items()):
        return None
    given = {n for n in ("intrinsics", "depth_scale")   # values chosen on the command line are not compared
             if ctx.get_parameter_source(n) in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT)}
    return {"config": str(config), "sequence": str(ctx.params.get("sequence")), "frames": dataset.get("frames"),
            "frame_names_sha256": dataset.get("frame_names_sha256"),
            "K": None if "intrinsics" in given else dataset.get("K"),
            "depth_scale": None if "depth_scale" in given else dataset.get("depth_scale"),
            "ground_truth_sha256": dataset.get("ground_truth_sha256")}


def _replayable(param: click.Parameter) -> bool:
    return param.name not in NOT_REPLAYED and not isinstance(param, DeprecatedAlias) and param.expose_value


# --------------------------------------------------------------------------------------------------
# --config RUN/config.json: the options of an earlier run as click's default_map
# --------------------------------------------------------------------------------------------------
def load_replay_config(path: str | os.PathLike, command: click.Command) -> dict[str, Any]:
    """The ``parameters`` of a config.json written by ``command``, checked: JSON, the same command, this
    version of the contract, only known keys. Values None (= the option's default) are left out."""
    return read_replay_config(path, command)[1]


def read_replay_config(path: str | os.PathLike, command: click.Command) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(document, parameters)`` of a config.json written by ``command`` (:func:`load_replay_config`)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigFileError(f"{path}: cannot read it ({exc.strerror or exc}); pass RUN/config.json of an earlier "
                              "run") from None
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        # JSONDecodeError, and what Python's reader refuses for structural reasons: numbers of more than 4300
        # digits (ValueError), nesting deeper than the recursion limit (RecursionError)
        why = "nested too deeply for Python's JSON reader" if isinstance(exc, RecursionError) else shorten(str(exc))
        raise ConfigFileError(f"{path}: not a JSON file radiomap can read ({why}); pass the config.json a radiomap "
                              "run wrote") from None
    if not isinstance(doc, dict):
        raise ConfigFileError(f"{path}: holds a JSON {type(doc).__name__}, not the object a radiomap run writes; "
                              "pass the config.json a reconstruct or compare run wrote")
    if "config_version" not in doc and isinstance(doc.get("method"), dict) and "part_of" in doc:
        method, top = doc["method"].get("name", "?"), doc["part_of"]
        if not top:     # a comparison that wrote no config.json (radiomap demo's)
            raise ConfigFileError(f"{path}: the record of method {method!r} of a comparison that wrote no replayable "
                                  "config.json (e.g. radiomap demo's), not a run's config; run that command again")
        raise ConfigFileError(f"{path}: the record of method {method!r} of a comparison, not a run's config; replay "
                              f"the comparison: radiomap compare --config {top} --methods {method} -o OUT")
    if "config_version" not in doc and "FixedPoses" in str(doc.get("dataset")):   # a method folder written before
        # part_of was recorded: its dataset the repr of mapping.compare.run.FixedPoses
        top = path.parent.parent / "config.json"
        raise ConfigFileError(f"{path}: the record of a method folder of a comparison, not a run's config; replay the "
                              f"comparison: radiomap compare --config {top} --methods {path.parent.name} -o OUT")
    if "config_version" not in doc:
        raise ConfigFileError(f"{path}: no key 'config_version' (written before radiomap replayed runs, or not by "
                              "radiomap); it cannot be replayed: give its options on the command line")
    if doc["config_version"] != CONFIG_VERSION:
        raise ConfigFileError(f"{path}: key 'config_version' is {doc['config_version']!r}, this radiomap "
                              f"{__version__} replays version {CONFIG_VERSION}; run the radiomap that wrote it, or "
                              "give the options on the command line")
    if doc.get("command") != command.name:
        raise ConfigFileError(f"{path}: key 'command' is {doc.get('command')!r}, not {command.name!r}; replay it "
                              f"with 'radiomap {doc.get('command')} --config {path}'")
    for key in doc:
        if key not in CONFIG_INFO_KEYS:
            where = " (options go under 'parameters')" if key in {p.name for p in command.params} else ""
            raise ConfigFileError(f"{path}: unknown key {key!r}{where}; remove it")
    params = doc.get("parameters")
    if not isinstance(params, dict):
        raise ConfigFileError(f"{path}: key 'parameters' must be an object of options, got {type(params).__name__}")
    names = {p.name for p in command.params if _replayable(p)}
    renamed = {p.old.lstrip("-").replace("-", "_"): p.target for p in command.params if isinstance(p, DeprecatedAlias)}
    for key in params:
        if key not in names:
            hint = (f" (renamed {renamed[key]!r})" if key in renamed else
                    " (not replayed: give it on the command line)" if key in NOT_REPLAYED else "")
            raise ConfigFileError(f"{path}: unknown key 'parameters.{key}' for radiomap {command.name}{hint}; "
                                  "remove or rename it")
    return doc, {k: v for k, v in params.items() if v is not None}


def _load_config(ctx: click.Context, param: click.Parameter, value):
    if value is None or ctx.resilient_parsing:
        return value
    doc, params = read_replay_config(value, ctx.command)
    ctx.default_map = {**(ctx.default_map or {}), **params,
                       **ctx.meta.get(_META_ALIAS_VALUES, {})}   # an old spelling given here beats the file
    ctx.meta[_META_CONFIG] = value
    ctx.meta[_META_RECORD] = doc
    return value


def config_option(f):
    """``--config RUN/config.json``: replay a run (its options as defaults; the command line overrides them)."""
    return click.option("--config", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
                        is_eager=True, callback=_load_config, expose_value=False, metavar="RUN/config.json",
                        help="Replay a run: take every option from the config.json it wrote (options given on the "
                             "command line override it; -o defaults to the run's own folder, refused without "
                             "--force).")(f)


def drop_replayed(ctx: click.Context, name: str, default: Any, why: str) -> bool:
    """A value from ``--config`` that an option given on the command line contradicts (``--surfel-mesh`` of a
    surfel run replayed with ``--backend tsdf``) is dropped with a note on stderr, since the command line has
    no way to unset it; True if it was. A contradiction on the command line itself stays an error."""
    if ctx.get_parameter_source(name) is not ParameterSource.DEFAULT_MAP:
        return False
    click.echo(f"note: {ctx.meta.get(_META_CONFIG)}: {name} {ctx.params.get(name)!r} is not used ({why})", err=True)
    ctx.params[name] = default
    return True


# --------------------------------------------------------------------------------------------------
# renamed options: the old spelling stays as a hidden alias that warns
# --------------------------------------------------------------------------------------------------
class DeprecatedAlias(click.Option):
    """A hidden option spelling ``old`` that sets the option named ``target`` (its value converted and checked
    by the target's type and callback) and warns in one line. Needs :class:`RadiomapCommand`."""

    def __init__(self, param_decls, *, target: str, new: str, note: str = "", **attrs) -> None:
        super().__init__(param_decls, hidden=True, **attrs)
        self.old, self.target, self.new, self.note = param_decls[0], target, new, note


def deprecated_alias(old: str, target: str, new: str, note: str = ""):
    """Decorator: ``old`` (e.g. ``--reference-exposure``) keeps working as a hidden, deprecated spelling of the
    option whose parameter is ``target`` and whose spelling is ``new``."""
    name = f"deprecated_{old.lstrip('-').replace('-', '_')}"
    return click.option(old, name, cls=DeprecatedAlias, target=target, new=new, note=note, default=None,
                        metavar="VALUE")


class RadiomapCommand(click.Command):
    """A subcommand that resolves :class:`DeprecatedAlias` options, records its argv for config.json and names
    the config file and key when a ``--config`` value is refused."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta[_META_ARGV] = ["radiomap", ctx.info_name, *args]
        aliased = self._resolve_aliases(ctx, args)
        try:
            rest = super().parse_args(ctx, args)
        except ImplausibleValueError as exc:   # a Number option: name the config key when the value came from it
            config = ctx.meta.get(_META_CONFIG)
            name = next((p.name for p in self.params if isinstance(p.type, Number) and
                         ctx.get_parameter_source(p.name) is ParameterSource.DEFAULT_MAP and
                         max(p.opts, key=len) in str(exc)), None) if config is not None else None
            if name is None:
                raise
            raise ConfigFileError(f"{config}: key 'parameters.{name}': {exc} (fix it there or give it on the "
                                  "command line)") from None
        except click.BadParameter as exc:
            if exc.param is not None and exc.param.name in aliased:
                raise click.BadParameter(exc.message, ctx=ctx, param_hint=aliased[exc.param.name]) from None
            config = ctx.meta.get(_META_CONFIG)
            if config is None or exc.param is None or \
                    ctx.get_parameter_source(exc.param.name) is not ParameterSource.DEFAULT_MAP:
                raise
            spelling = exc.param.opts[0] if isinstance(exc.param, click.Option) else exc.param.human_readable_name
            raise ConfigFileError(f"{config}: key 'parameters.{exc.param.name}': {exc.format_message()} (fix it "
                                  f"there or give {spelling} on the command line)") from None
        for alias in self.params:
            if isinstance(alias, DeprecatedAlias):
                ctx.params.pop(alias.name, None)
        for name in aliased:
            ctx.set_parameter_source(name, ParameterSource.COMMANDLINE)
        return rest

    def _resolve_aliases(self, ctx: click.Context, args: list[str]) -> dict[str, str]:
        """Old spellings on the command line become the new option's value (through the default map, below the
        command line and above a config file, so that the new option's type, callback and required check
        apply); returns {target parameter: old spelling}."""
        aliases = [p for p in self.params if isinstance(p, DeprecatedAlias)]
        if not aliases or ctx.resilient_parsing:
            return {}
        opts, _, _ = self.make_parser(ctx).parse_args(args=list(args))  # a dry run: nothing is processed
        aliased = {}
        unset = getattr(click.core, "UNSET", None)  # click >= 8.3 marks a value not given
        for alias in aliases:
            if opts.get(alias.name, unset) in (None, unset):
                continue
            if opts.get(alias.target, unset) not in (None, unset):
                raise click.UsageError(f"{alias.old} is the old spelling of {alias.new}; give only {alias.new}", ctx)
            click.echo(f"warning: {alias.old} is deprecated, use {alias.new}"
                       + (f" ({alias.note})" if alias.note else ""), err=True)
            aliased[alias.target] = alias.old
            ctx.meta.setdefault(_META_ALIAS_VALUES, {})[alias.target] = opts[alias.name]
        ctx.default_map = {**(ctx.default_map or {}), **ctx.meta.get(_META_ALIAS_VALUES, {})}
        return aliased


class PoseSource(click.ParamType):
    """``--poses``: ``icp``, ``gt`` or a trajectory (a TUM file, a Redwood ``.log``, a folder of 7-Scenes pose files;
    :mod:`mapping.pose_files`), which becomes a Path (recorded absolute in config.json). A relative path that is not
    found from the working folder is looked for in the command's SEQUENCE (``--poses CameraTrajectory.txt`` in a
    batch: each sequence its own file)."""

    name = "icp|gt|FILE"

    def convert(self, value, param, ctx):
        if isinstance(value, os.PathLike) or value in ("icp", "gt"):
            return value
        path = Path(str(value))
        if not path.exists() and path.is_absolute():
            self.fail(f"{value!r} is neither icp, gt nor an existing trajectory (a TUM file, a Redwood .log, a folder "
                      "of 7-Scenes pose files); check the path", param, ctx)
        return path   # a relative path may be the sequence's own file: pose_arguments() resolves it


def pose_options(default: str, help_text: str):
    """``--poses`` (:class:`PoseSource`, ``default``) and ``--poses-max-difference`` (seconds between a frame and the
    pose of a TUM trajectory file it takes)."""
    def decorate(f):
        f = click.option("--poses-max-difference", default=None, metavar="SECONDS",
                         type=Number(POSE_TIME_DIFFERENCE_S, "s", "a frame and its pose, as evo's --t_max_diff"),
                         help="With --poses FILE (a TUM trajectory): the largest time difference between a frame and "
                              "the pose it takes, as evo's --t_max_diff [default: 0.02].")(f)
        return click.option("--poses", type=PoseSource(), default=default, show_default=True, help=help_text)(f)
    return decorate


def pose_arguments(ctx: click.Context) -> tuple[Any, float]:
    """The checked ``--poses`` and ``--poses-max-difference``: a relative trajectory path not found from the working
    folder is looked for in SEQUENCE (``--poses CameraTrajectory.txt`` in a batch: each sequence its own file);
    BadParameter when neither has it, for a negative difference, or a difference without a trajectory file."""
    poses = ctx.params.get("poses")
    if isinstance(poses, Path) and not poses.exists():
        own = Path(ctx.params["sequence"]) / poses if ctx.params.get("sequence") is not None else None
        if own is None or not own.exists():
            raise click.BadParameter(f"{str(poses)!r} is neither icp, gt nor an existing trajectory (a TUM file, a "
                                     "Redwood .log, a folder of 7-Scenes pose files), from here or in SEQUENCE; check "
                                     "the path", param_hint="--poses")
        ctx.params["poses"] = poses = own
    value = ctx.params.get("poses_max_difference")
    if value is None:
        return poses, 0.02
    if not (value >= 0 and value < float("inf")):
        raise click.BadParameter(f"must be a number of seconds >= 0, got {value}", param_hint="--poses-max-difference")
    if poses in ("icp", "gt") and not drop_replayed(ctx, "poses_max_difference", None, f"--poses {poses}"):
        raise click.BadParameter(f"applies with --poses FILE only (got --poses {poses}); drop it",
                                 param_hint="--poses-max-difference")
    return poses, float(value)


def settings_line(ctx: click.Context, settings: list[tuple]) -> str:
    """``settings: poses gt (compare's default; reconstruct's is icp), ...``: each ``(label, parameter, shown
    value[, what the default is called])`` with where the value came from (given, a config file, the default);
    for the defaults that differ between reconstruct and compare (:data:`DIFFERENT_DEFAULTS`) the other
    command's default is named. A parameter None: no source (a fixed behaviour)."""
    parts = []
    for label, name, shown, *default_name in settings:
        if isinstance(shown, os.PathLike):      # a file (--poses FILE): absolute, as config.json records it
            shown = os.path.abspath(os.fspath(shown))
        if name is None:
            parts.append(f"{label} {shown}")
            continue
        source = ctx.get_parameter_source(name)
        if source is ParameterSource.DEFAULT_MAP:
            how = f"from {ctx.meta.get(_META_CONFIG)}"
        elif source in (ParameterSource.COMMANDLINE, ParameterSource.ENVIRONMENT):
            how = "given"
        else:
            how = default_name[0] if default_name else f"{ctx.command.name}'s default"
            if name in DIFFERENT_DEFAULTS:
                other = next(c for c in DIFFERENT_DEFAULTS[name] if c != ctx.command.name)
                how += f"; {other}'s is {DIFFERENT_DEFAULTS[name][other]}"
        parts.append(f"{label} {shown} ({how})")
    return "settings: " + ", ".join(parts)


# Defaults that stay different between reconstruct and compare, as the summaries name them (a test checks
# them against the options): reconstruct maps real sequences (often without ground truth) and fuses what is
# best; compare measures corrections, so it keeps poses and method count fixed unless asked.
DIFFERENT_DEFAULTS = {
    "poses": {"reconstruct": "icp", "compare": "gt"},
    "exposure_compensation": {"reconstruct": "on with --response", "compare": "off"},
}


def refuse_sequence_as_output(sequence, output) -> None:
    """A results folder is never the sequence it is made from (``--force`` would clean result names in the input,
    and results would mix with the frames): :class:`radiometry.errors.OutputError` in one line."""
    from radiometry.errors import OutputError

    if sequence is not None and output is not None and \
            os.path.realpath(os.fspath(sequence)) == os.path.realpath(os.fspath(output)):
        raise OutputError(f"-o {output} is the input sequence {sequence}: the results would be written among its "
                          "frames; choose another output folder (e.g. a folder beside it); --force never writes into "
                          "an input")


def warn_far_depth(fraction: float, depth_max: float, *, threshold: float = 0.2) -> None:
    """Warn on stderr when more than ``threshold`` of the valid depth lay beyond ``--depth-max`` (ICP then
    sees fewer surfaces and may slide along what is left)."""
    if fraction > threshold:
        click.echo(f"warning: {100 * fraction:.0f} % of the valid depth lies beyond --depth-max {depth_max:g} m and "
                   "was neither fused nor tracked; raise --depth-max if the scene is deeper", err=True)


# --------------------------------------------------------------------------------------------------
# options alike in every command that reads an RGB-D sequence and fuses it (reconstruct, compare)
# --------------------------------------------------------------------------------------------------
def positive(ctx: click.Context, param: click.Parameter, value):
    """Option callback: a number that must be > 0 (None = not given)."""
    if value is not None and not value > 0:
        raise click.BadParameter(f"must be positive, got {value}")
    return value


def sequence_options(f):
    """--frames, --depth-scale, --intrinsics and --format: which frames of SEQUENCE and how to read them."""
    options = [
        click.option("--frames", type=FrameRange(), default=None, help="Frame range and stride A:B:S (e.g. 0:300:2)."),
        click.option("--depth-scale", type=Number(DEPTH_SCALE, "raw units per metre",
                                                  "1 for float metres, 1000 for millimetres, 5000 for TUM"),
                     default=None,
                     help="Raw depth units per metre [format default: TUM 5000, 7-Scenes/Redwood 1000]."),
        click.option("--intrinsics", type=str, default=None,
                     help="fx,fy,cx,cy or a file (3x3 matrix, 'fx fy cx cy', Open3D camera JSON) "
                          "[default: the sequence's own]."),
        click.option("--format", type=click.Choice(list(FORMATS)), default=None,
                     help="Sequence layout [default: detected]."),
    ]
    for option in reversed(options):
        f = option(f)
    return f


def fusion_options(f):
    """--backend, --voxel-size and --depth-max: the map the sequence is fused into."""
    options = [
        click.option("--backend", type=click.Choice(list(BACKENDS)), default="tsdf", show_default=True,
                     help="Fusion backend."),
        click.option("--voxel-size", type=Number(VOXEL_SIZE_M, "m", "1 mm for small objects, 5 mm-2 cm for rooms"),
                     default=0.01, show_default=True,
                     help="TSDF voxel size in metres."),
        click.option("--depth-max", type=Number(DEPTH_MAX_M, "m", "RGB-D cameras measure up to 4-10 m, 20 m at most"),
                     default=3.0, show_default=True,
                     help="Depth beyond this many metres is neither tracked nor fused."),
    ]
    for option in reversed(options):
        f = option(f)
    return f


def evaluation_options(f):
    """--holdout-every and --colour-map: what reconstruct and compare do with a map after fusion."""
    from mapping.colour_map import OPTIMISERS

    options = [
        click.option("--holdout-every", type=int, default=None, metavar="N",
                     help="Withhold every N-th frame from fusion and judge the final map by them: PSNR and L1 of the "
                          "map rendered at their poses (holdout.csv, metrics.json)."),
        click.option("--colour-map", type=click.Choice(list(OPTIMISERS)), default=None,
                     help="After fusion, optimise the mesh colours (in compare each method's) on the corrected frames "
                          "(Zhou & Koltun, Open3D): mesh_colourmap.ply beside mesh.ply if the held-out check keeps "
                          "it (colour_map.json)."),
    ]
    for option in reversed(options):
        f = option(f)
    return f


__all__ = ["CONFIG_VERSION", "ConfigFileError", "DIFFERENT_DEFAULTS", "DeprecatedAlias", "FrameRange", "Number",
           "PoseSource", "RadiomapCommand", "config_option", "deprecated_alias", "drop_replayed", "evaluation_options",
           "fusion_options", "load_replay_config", "pose_arguments", "pose_options", "positive",
           "read_replay_config", "refuse_sequence_as_output", "replay_manifest", "replayed_sequence", "run_manifest",
           "sequence_options", "settings_line", "warn_far_depth"]


class MeshFormats(click.ParamType):
    """``--formats ply,glb``: the mesh files a command writes, checked by
    :func:`mapping.validation.check_mesh_formats` as the option is parsed (an unknown name is one line naming the
    option and the accepted values, exit 1, before anything is read or written)."""

    name = "LIST"

    def convert(self, value, param, ctx):
        from mapping.validation import check_mesh_formats

        return check_mesh_formats(value, max(param.opts, key=len) if isinstance(param, click.Option) else "formats")


def formats_option(f):
    """``--formats``: the mesh files of reconstruct, compare, demo (and batch through them); PLY by default."""
    return click.option(
        "--formats", type=MeshFormats(), default="ply", show_default=True,
        help="Mesh files to write, comma-separated: ply (sRGB-encoded display colours: MeshLab, Blender, Open3D, "
             "trimesh), glb (binary glTF, linear COLOR_0: three.js and other glTF viewers), obj, npz "
             "(mesh_colours.npz: map-unit colours, for evaluation). docs/outputs.md: which file for which tool. "
             "The surfel backend writes PLY only.")(f)


def check_formats(ctx: click.Context, formats: tuple[str, ...], backend: str, *, spelling: str = "--formats"
                  ) -> tuple[str, ...]:
    """``--formats`` checked against ``--backend``: the surfel backend writes PLY files only (surfels.ply, and
    surfels_mesh. py with --surfel-mesh), so other formats asked for are a usage error rather than silently not
    written (a replayed value is dropped with a note: :func:`drop_replayed`)."""
    extra = [f for f in formats if f != "ply"]
    if backend == "surfel" and extra and not drop_replayed(ctx, "formats", ("ply",), "--backend surfel"):
        raise click.BadParameter(f"{','.join(extra)}: the surfel backend writes PLY files only (surfels.ply, and "
                                 f"surfels_mesh.ply with --surfel-mesh); drop {spelling} or use --backend tsdf",
                                 param_hint=spelling)
    return ("ply",) if backend == "surfel" else formats


def _size_text(n: int) -> str:
    for unit, scale in (("GB", 2 ** 30), ("MB", 2 ** 20), ("kB", 2 ** 10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def written_text(folder: Path, *, limit: int = 12) -> str:
    """What a command wrote into ``folder``: one line per file or folder at its top (folders with their file
    count), biggest first, at most ``limit`` (the rest summed in one line), and the total. Hidden entries and the
    lock are left out (they are bookkeeping). Printed at the end of reconstruct, compare, demo and batch."""
    from mapping.export import LOCK_NAME

    folder = Path(folder)
    if not folder.is_dir():
        return ""
    rows = []
    for entry in folder.iterdir():
        if entry.name.startswith(".") or entry.name == LOCK_NAME:
            continue
        if entry.is_dir() and not entry.is_symlink():
            files = [p for p in entry.rglob("*") if p.is_file() and not p.is_symlink()]
            rows.append((sum(p.stat().st_size for p in files), f"{entry.name}/ ({len(files)} files)"))
        elif entry.is_file():
            rows.append((entry.stat().st_size, entry.name))
    rows.sort(key=lambda r: (-r[0], r[1]))
    shown, rest = rows[:limit], rows[limit:]
    width = max((len(name) for _, name in shown), default=0)
    lines = [f"wrote {folder}: {_size_text(sum(n for n, _ in rows))}"]
    lines += [f"  {name:<{width}}  {_size_text(n):>9}" for n, name in shown]
    if rest:
        lines.append(f"  ... {len(rest)} more  {_size_text(sum(n for n, _ in rest))}")
    return "\n".join(lines)


def written_files_text(paths) -> str:
    """What a command wrote as separate files (``radiomap vignetting``): one line per file with its size, and the
    total."""
    files = [Path(p) for p in paths if p is not None and Path(p).is_file()]
    if not files:
        return ""
    sizes = [f.stat().st_size for f in files]
    width = max(len(str(f)) for f in files)
    return "\n".join([f"wrote {len(files)} file{'s' if len(files) != 1 else ''}: {_size_text(sum(sizes))}"] +
                     [f"  {str(f):<{width}}  {_size_text(n):>9}" for f, n in zip(files, sizes)])
