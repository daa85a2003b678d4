"""``radiomap demo``: the options of :func:`mapping.demo.run_demo` (the steps, the layout and the OUT policy
are described there) and the printing of its summary."""

from __future__ import annotations

from pathlib import Path

import click

from mapping.cli._common import formats_option, written_text
from mapping.demo import DEMO_CAMERAS, run_demo, summary_text
from mapping.factory import BACKENDS

EPILOG = """\b
Examples:
  radiomap demo
      the full demo into ./demo_out (about 1 minute on 2 idle cores, 2 when they are busy)
  radiomap demo -o /tmp/demo --quick
      a reduced demo (160x120, 15 frames) in 10-30 s
\b
OUT/compare/report.html shows everything: the table, the histograms (Fig. 9 of Alexandrov et al.), the
meshes side by side and the calibration accuracy. OUT/demo.txt repeats what is printed. An earlier
demo in OUT, or any other non-empty folder, is refused without --force.
"""


@click.command("demo", epilog=EPILOG)
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), default=Path("demo_out"),
              show_default=True, help="Folder for everything the demo generates.")
@click.option("--quick", is_flag=True, help="A reduced demo (160x120, 15 room frames, 60 sweep frames) for CI.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Seed of every simulation (same seed, same results).")
@click.option("--backend", type=click.Choice(list(BACKENDS)), default="tsdf", show_default=True,
              help="Fusion backend.")
@click.option("--camera", type=click.Choice(DEMO_CAMERAS), default="asymmetric", show_default=True,
              help="Simulated camera: 'asymmetric' (strong non-radial vignetting, where the LUT beats the "
                   "polynomial), 'xtion' (the paper's nearly radial Xtion), 'mild'.")
@click.option("--exposure-compensation/--no-exposure-compensation", "exposure_compensation", default=True,
              help="Compensate auto exposure [default: on].")
@formats_option
@click.option("--all-meshes", is_flag=True,
              help="Write every method's mesh (about 14 MB each at the default size), not only those of 'none' and "
                   "the LUT correction (the others are measured and rendered all the same).")
@click.option("--force", is_flag=True, help="Overwrite an earlier demo in OUTPUT (or write into another non-empty "
                                            "folder; files that are not the demo's are kept).")
@click.option("--no-progress", is_flag=True, help="No progress bars.")
def command(output: Path, quick: bool, seed: int, backend: str, camera: str, exposure_compensation: bool,
            formats: tuple[str, ...], all_meshes: bool, force: bool, no_progress: bool) -> None:
    """Simulate a camera with strong vignetting and auto exposure, calibrate its response and vignetting,
    reconstruct a simulated room with no correction, polynomial and LUT vignetting correction, and compare
    them (table, histograms, meshes, HTML report). Needs no data."""
    result = run_demo(output, quick=quick, seed=seed, force=force, exposure_compensation=exposure_compensation,
                      backend=backend, camera=camera, progress=not no_progress,
                      log=lambda msg: click.echo(msg, err=True), mesh_formats=formats,
                      all_meshes=all_meshes)
    click.echo(summary_text(result))
    click.echo(written_text(output), err=True)
