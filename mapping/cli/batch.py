"""``radiomap batch {reconstruct|compare|self-calibrate} LIST -o OUT -- [options]``: one command on many sequences,
on Ray or on local processes, resumable, with a summary across sequences (``mapping.batch``; a command joins with an
entry in ``mapping.batch.COMMANDS`` and a ``task_arguments`` function in its own CLI module)."""

from __future__ import annotations

from pathlib import Path

import click

EPILOG = """\b
Examples:
  radiomap batch reconstruct scans.txt -o runs -- --response crf.npz --vignetting vgn.npz --poses gt
      every sequence folder listed in scans.txt (one a line) into runs/<name>/, as 'radiomap reconstruct
      SEQUENCE -o runs/<name> --response crf.npz ...' writes it; runs/summary.csv and runs/index.html
  radiomap batch compare scans.txt -o cmp --workers 2 -- -r crf.npz --vignetting-lut lut.npz
      a comparison per sequence, two at a time
  ray start --head                                   (on the head node; 'ray start --address=HEAD:6379' on the others)
  radiomap batch reconstruct scans.txt -o /shared/runs --address auto -- -r /shared/crf.npz
      on a Ray cluster: the sequences, the models and OUT on storage every node sees
\b
Run it again to resume: complete results folders are skipped, folders of runs that did not finish (killed,
failed) or that miss a file are run again, and a folder keeps its name. A complete folder made with other
options (or by another command) is refused before anything runs: give another -o, or --force. Each task's
output is in OUT/logs/<name>.log. Options after -- are those of 'radiomap COMMAND' (all but SEQUENCE, -o and
--force).
"""

#: options of the command that the batch sets itself
_OWN = {"-o": "-o OUT of batch (each sequence gets OUT/<name>)", "--output": "-o OUT of batch (each sequence gets "
        "OUT/<name>)", "--force": "--force of batch (complete sequences are otherwise skipped)"}


@click.command("batch", epilog=EPILOG, context_settings={"max_content_width": 100})
@click.argument("command_name", metavar="COMMAND")
@click.argument("sequence_list", metavar="LIST", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("options", nargs=-1, type=click.UNPROCESSED, metavar="-- [OPTIONS OF COMMAND]")
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder of the batch: OUT/<name>/ per sequence, OUT/summary.csv, OUT/index.html, OUT/logs/.")
@click.option("--workers", type=click.IntRange(1), default=None, metavar="N",
              help="Sequences at once [default: one per core; on a Ray cluster, its CPUs // --threads].")
@click.option("--threads", type=click.IntRange(1), default=None, metavar="T",
              help="Threads of each task (Open3D, Numba, BLAS) [default: this machine's cores // N; 1 on a cluster].")
@click.option("--engine", type=click.Choice(["auto", "ray", "processes"]), default="auto", show_default=True,
              help="ray: a Ray instance (local, or the cluster at --address); processes: child processes of this "
                   "one; auto: Ray when it is installed (pip install 'radiomap[cluster]').")
@click.option("--address", default=None, metavar="ADDR",
              help="Join a running Ray cluster: auto (the one 'ray start' made on this machine) or HOST:PORT.")
@click.option("--force", is_flag=True, help="Run complete sequences again too (also those made with other options).")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
def command(command_name: str, sequence_list: Path, options: tuple[str, ...], output: Path, workers: int | None,
            threads: int | None, engine: str, address: str | None, force: bool, no_progress: bool) -> None:
    """Run COMMAND (reconstruct, compare or self-calibrate) on every sequence folder listed in LIST, one task per
    sequence, each result in OUT/<name>/ exactly as 'radiomap COMMAND' writes it."""
    from mapping.batch import (COMMANDS, BatchError, Task, folder_names, read_sequence_list, run_batch,
                               summary_rows, write_summary)
    from mapping.batch.report import columns_of
    from mapping.cli import SUBCOMMANDS
    from radiometry.tables import format_table

    if command_name not in COMMANDS:
        raise BatchError(f"radiomap batch runs {', '.join(COMMANDS)}, not {command_name!r}")
    for token in options:
        key = token.split("=", 1)[0]
        if key in _OWN or (token.startswith("-o") and not token.startswith("--")):
            raise click.UsageError(f"{token} is not an option of the command here: give {_OWN.get(key, _OWN['-o'])}")
    sequences = read_sequence_list(sequence_list)
    names, notes = folder_names(sequences, output)   # a folder keeps its sequence across resumes
    for line in notes:
        click.echo(line, err=True)
    ctx = click.get_current_context()
    cmd = SUBCOMMANDS[command_name]
    task_arguments = __import__(cmd.callback.__module__, fromlist=["task_arguments"]).task_arguments
    tasks = []
    for sequence, name in zip(sequences, names):
        args = [str(sequence), "-o", str(output / name), *options]
        with cmd.make_context(command_name, args, parent=ctx) as sub:     # the command's own parsing and checks
            tasks.append(Task(name, command_name, sequence, output / name, task_arguments(sub)))

    def report(outcome) -> None:
        task = outcome.task
        if outcome.status == "skipped":
            click.echo(f"{task.name}: skipped, complete in {task.output} (--force runs it again)")
        elif outcome.status == "complete":
            click.echo(f"{task.name}: complete in {outcome.seconds:.1f} s")
        else:
            click.echo(f"{task.name}: failed: {outcome.error}", err=True)

    outcomes = run_batch(tasks, output, workers=workers, threads=threads, engine=engine, address=address,
                         force=force, progress=not no_progress, notify=report,
                         note=lambda line: click.echo(line, err=True))
    files = write_summary(outcomes, output, title=f"radiomap batch {command_name}: {sequence_list.name}")
    rows = summary_rows(outcomes)
    shown = [{k: "-" if v is None else v for k, v in row.items()} for row in rows]
    click.echo(format_table(shown, [c for c in columns_of(rows) if c != "error"]))
    click.echo(f"summary: {files['csv']}, {files['html']}")
    from mapping.cli._common import written_text

    click.echo(written_text(output), err=True)
    failed = [o.task.name for o in outcomes if o.status == "failed"]
    if failed:
        click.echo(f"radiomap: error: {len(failed)} of {len(outcomes)} sequences failed ({', '.join(failed)}); "
                   f"their logs are in {output / 'logs'}; run the same command again to retry them", err=True)
        ctx.exit(1)
