"""The ``radiomap`` command's entry point: Ctrl-C or SIGTERM while the program is still importing its libraries ends
with one line, as during a run (:func:`mapping.cli.main` handles everything after the imports)."""

from __future__ import annotations

import signal
import sys

_TERMINATED = False


def _terminate(signum, frame) -> None:  # noqa: ANN001 - a signal handler
    global _TERMINATED
    _TERMINATED = True
    raise KeyboardInterrupt


def main() -> int:
    own = signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    if own:
        signal.signal(signal.SIGTERM, _terminate)
    try:
        from mapping.cli import main as run
    except KeyboardInterrupt:
        sys.stderr.write("radiomap: terminated (SIGTERM)\n" if _TERMINATED else "radiomap: interrupted\n")
        return 128 + signal.SIGTERM if _TERMINATED else 130
    if own:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # mapping.cli.main installs its own
    return run()
