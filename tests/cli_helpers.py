"""Small helpers shared by the command-line tests."""

from __future__ import annotations


def error_line(result) -> str:
    """The one ``radiomap: error:`` line of a run that exited 1 (asserting both)."""
    assert result.exit_code == 1, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("radiomap: error:")]
    assert len(lines) == 1, result.output
    return lines[0]
