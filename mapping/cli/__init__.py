"""The ``radiomap`` command: one group, lazily imported subcommands, one-line errors.

Each subcommand lives in its own module ``mapping/cli/<name>.py`` exposing a ``click.Command`` named
``command``; heavy imports (open3d, matplotlib, scipy) stay inside the command functions so that
``radiomap --help`` and ``radiomap --version`` are instant.
"""

from __future__ import annotations

import logging
import sys

import click

from radiometry import __version__
from radiometry.errors import RadiomapError
from radiometry.registry import Registry

#: name -> the subcommand (imported on first use), in the order the help lists them
SUBCOMMANDS = Registry("command", {name: f"mapping.cli.{name}:command" for name in
                                   ("demo", "response", "simulate", "vignetting", "correct", "reconstruct", "compare",
                                    "batch")}
                       | {"self-calibrate": "mapping.cli.self_calibrate:command"})

EPILOG = """\b
Examples:
  radiomap demo -o demo_out
      simulate a camera and a room, calibrate, reconstruct and compare (no data needed)
  radiomap response data_samples/brackets --times data_samples/brackets/times.txt -o crf.npz
      recover the camera response from bracketed exposures (auto: Debevec's data term with a log-log prior)
  radiomap simulate paper -o paper_seq --seed 1
      render a white-paper vignetting calibration sweep with known ground truth
  radiomap vignetting paper_seq/rgb --response crf.npz -o vignetting.npz --model lut
      calibrate vignetting from a white-paper sweep
  radiomap correct frames/ --response crf.npz --vignetting vignetting.npz -o corrected/
      remove vignetting from images or a video
  radiomap reconstruct room_seq --response crf.npz --vignetting vignetting.npz --poses gt -o run1
      fuse irradiance into a TSDF map, export a mesh and the colour-disagreement histogram
  radiomap reconstruct --config run1/config.json -o run2 --voxel-size 0.02
      replay run1 with its recorded options, one of them changed (compare --config likewise)
  radiomap self-calibrate room_seq --response crf.npz --poses gt -o selfcal
      vignetting, exposure and white balance from the sequence itself (no white sheet)
  radiomap batch reconstruct scans.txt -o runs -- --response crf.npz --poses gt
      every listed sequence, one task each, on Ray or local processes (resumable)
\b
Option names mean one thing everywhere: -o output, -r response, --vignetting a model file, --frames a
range A:B:S, -n/--num-frames a count, --format a sequence layout; -v is only 'radiomap -v COMMAND'
(verbose). Old spellings (-v FILE, --reference-exposure, --exposure-reference, simulate --frames N, ...)
still work and warn.

Run 'radiomap COMMAND --help' for the options of a command.
"""


class LazyGroup(click.Group):
    """A group whose subcommands are imported on first use and whose known errors print one line."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(SUBCOMMANDS) + sorted(set(self.commands) - set(SUBCOMMANDS))

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name in self.commands:
            return self.commands[cmd_name]
        return SUBCOMMANDS[cmd_name] if cmd_name in SUBCOMMANDS else None

    def resolve_command(self, ctx: click.Context, args: list[str]):
        name = args[0]
        if not ctx.resilient_parsing and not name.startswith("-") and self.get_command(ctx, name) is None:
            raise click.UsageError(f"No such command {name!r}; choose one of {', '.join(self.list_commands(ctx))}",
                                   ctx)
        return super().resolve_command(ctx, args)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except RadiomapError as exc:
            _error(ctx, str(exc))
        except click.ClickException as exc:   # click's usage errors quote the value given: cut it too
            from radiometry.errors import shorten

            exc.message = shorten(exc.message)
            raise
        except KeyboardInterrupt:
            _interrupted(ctx)
        except MemoryError:
            _error(ctx, "out of memory; use a larger --voxel-size, a shorter --frames range or a smaller --depth-max")
        except RecursionError:   # a structure nested too deeply for Python (a JSON file, say): one line, not 1000
            _error(ctx, "input nested too deeply to read (Python's recursion limit); check the files given")
        except OSError as exc:
            if _INTERRUPTED:
                _interrupted(ctx)
            # an operating-system limit that no reader turned into a RadiomapError: the path and the reason
            where = exc.filename if exc.filename is not None else "a file"
            _error(ctx, f"cannot use {where}: {exc.strerror or exc}; {_os_fix(exc)}")
        except RuntimeError as exc:
            if _INTERRUPTED:
                _interrupted(ctx)
            if "[Open3D Error]" not in str(exc):
                raise
            from mapping._open3d import open3d_message  # open3d is loaded: it raised

            logging.getLogger("radiomap").debug("Open3D error", exc_info=True)
            _error(ctx, f"Open3D failed: {open3d_message(exc)} (check the input and the options; -vv logs the "
                        "details)")
        except Exception:
            if _INTERRUPTED:  # whatever Ctrl-C broke on its way (an import cut half-way raises ImportError later)
                _interrupted(ctx)
            raise


#: set by the SIGINT/SIGTERM handlers (the signal's number): an exception raised after the signal is a consequence of
#: it, reported as the interruption
_INTERRUPTED = 0


def _on_sigint(signum, frame):
    """Ctrl-C (and SIGTERM, where it had its default action) unwind the command like KeyboardInterrupt, so that
    locks are released and staged files removed; the signal is noted for the message and the exit code."""
    global _INTERRUPTED
    _INTERRUPTED = signum
    raise KeyboardInterrupt


def _error(ctx: click.Context, message: str) -> None:
    from radiometry.errors import shorten

    click.echo(f"radiomap: error: {shorten(message)}", err=True)
    ctx.exit(1)


def _interrupted(ctx: click.Context) -> None:
    import signal

    if _INTERRUPTED == signal.SIGTERM:
        click.echo("radiomap: terminated (SIGTERM)", err=True)
        ctx.exit(128 + signal.SIGTERM)
    click.echo("radiomap: interrupted", err=True)
    ctx.exit(130)


def _os_fix(exc: OSError) -> str:
    import errno

    return {errno.ENAMETOOLONG: "use a shorter name or path",
            errno.EMFILE: "raise the limit of open files (ulimit -n) or give fewer files",
            errno.ENFILE: "the system has too many files open; close some programs and retry",
            errno.EACCES: "check the path and its permissions", errno.EPERM: "check the path and its permissions",
            errno.EROFS: "the file system is read-only; choose another output folder",
            errno.ENOSPC: "the disk is full; free some space or choose another output folder",
            errno.ELOOP: "a symbolic link loops; fix the link",
            errno.ENOTDIR: "a part of the path is a file, not a folder; check the path"}.get(
        exc.errno, "check the path and the system's limits")


#: the loggers -v/-vv open up: radiomap's own (``logging.getLogger(__name__)`` in both packages, and the CLI's)
OWN_LOGGERS = ("radiometry", "mapping", "radiomap")


def configure_logging(verbose: int) -> None:
    """``-v`` INFO, ``-vv`` DEBUG for radiomap's own loggers only; everything else (matplotlib's font manager,
    numba, PIL, ray, urllib3, ...) stays at WARNING, as the root logger is. One handler on stderr."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    # without -v radiomap's loggers follow the root (WARNING here; a program embedding the CLI keeps its own setting)
    level = logging.NOTSET if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    for name in OWN_LOGGERS:
        logging.getLogger(name).setLevel(level)


def _print_version(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    if not value or ctx.resilient_parsing:
        return
    from mapping._native import summary

    click.echo(f"radiomap {__version__}\nkernels: {summary()}")
    ctx.exit()


@click.group(cls=LazyGroup, epilog=EPILOG, context_settings={"help_option_names": ["-h", "--help"],
                                                             "max_content_width": 100})
@click.option("--version", "-V", is_flag=True, expose_value=False, is_eager=True, callback=_print_version,
              help="Show the version and the kernels in use (compiled C or Numba), and exit.")
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug), before the command: "
                                                   "radiomap -v reconstruct ...")
def cli(verbose: int) -> None:
    """radiomap: radiometric calibration and irradiance fusion for RGB-D maps.

    Calibrate a camera's response and vignetting, undo them (and auto exposure), and fuse physically
    meaningful irradiance into TSDF or surfel maps; measure colour coherence like Alexandrov et al.
    """
    configure_logging(verbose)
    from radiometry._native import choice, compiled

    if choice() == "c":  # a wrong RADIOMAP_KERNELS fails here, before a command writes anything
        compiled("mapping._ckernels")
        compiled("radiometry._ckernels")


def main(argv: list[str] | None = None) -> int:
    import signal
    import threading

    if threading.current_thread() is threading.main_thread() and \
            signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _on_sigint)     # not where SIGINT is ignored (a shell's background job)
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _on_sigint)
    try:
        cli.main(args=argv, prog_name="radiomap", standalone_mode=True)
    except SystemExit as exc:
        return int(exc.code or 0) if not isinstance(exc.code, str) else 1
    except KeyboardInterrupt:       # outside a command (click's own handling): still one line
        terminated = _INTERRUPTED == signal.SIGTERM
        click.echo("radiomap: terminated (SIGTERM)" if terminated else "radiomap: interrupted", err=True)
        return 128 + signal.SIGTERM if terminated else 130
    finally:
        if signal.getsignal(signal.SIGINT) is _on_sigint:
            # the run is over: as the program (argv from the command line), a late Ctrl-C at exit is ignored
            signal.signal(signal.SIGINT, signal.SIG_IGN if argv is None else signal.default_int_handler)
        if signal.getsignal(signal.SIGTERM) is _on_sigint:
            signal.signal(signal.SIGTERM, signal.SIG_IGN if argv is None else signal.SIG_DFL)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
