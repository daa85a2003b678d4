"""``radiomap simulate {room,paper,brackets}``: render sequences with known ground truth (a room can
hang the user's own pictures on its walls with ``--picture``)."""

from __future__ import annotations

import time
from pathlib import Path

import click

from mapping.cli._common import Number, RadiomapCommand, deprecated_alias
from mapping.validation import EXPOSURE_TIME_S, FLICKER, LENS_APERTURE, LENS_FOCAL_MM, LIGHT_CHANGE

KIND_DEFAULT_FRAMES = {"room": 100, "paper": 300, "brackets": 9}

EPILOG = """\b
Examples:
  radiomap simulate room -o room_seq --seed 1
      100 frames of a furnished room, 640x480, auto exposure and white balance, TUM layout + truth
  radiomap simulate room -o room_fixed --seed 1 --fixed-exposure -n 300 --light-change 0.5
      fixed exposure; the light dims to half its brightness in the middle of the sequence
  radiomap simulate room -o room_art --seed 1 --picture holiday.jpg --picture map.png
      your own pictures hung on the walls (image textures; the paths are recorded in truth/room.json)
  radiomap simulate paper -o paper_seq --seed 1 --flicker 0.05
      a white-paper sweep for vignetting calibration (fixed exposure), light flickering by 5 %
  radiomap simulate brackets -o brackets --seed 1 -n 11
      11 exposures of an HDR chart, 1/1000 s doubling to 1.024 s, and times.txt
  radiomap simulate paper -o euroc_paper --crf ../shared/data/vignetting/euroc_mt9v034_752x480/pcalib.txt \\
      --vignette-png ../shared/data/vignetting/euroc_mt9v034_752x480/vignette.png
      a real camera's response and vignetting
  radiomap simulate room -o lens --lensfun "EF-S 10-22" --lens-focal 10 --lens-aperture 3.5
      vignetting of a lens from the lensfun database

\b
The ground truth (response, vignetting, per-frame exposure and gains, camera, scene) is written to
DIR/truth/; DIR/radiomap_sequence.json describes the sequence.
"""


@click.command("simulate", cls=RadiomapCommand, epilog=EPILOG, context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("kind", type=click.Choice(["brackets", "paper", "room"]))
@click.option("-o", "--output", "output", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Folder for the sequence (must be empty or absent unless --force).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Seed of everything random (scene, trajectory, noise): same seed, same bytes.")
@click.option("-n", "--num-frames", type=click.IntRange(min=1), default=None, metavar="N",
              help="How many frames (room: 100, paper: 300) or exposures (brackets: 9) to render.")
@click.option("--width", type=click.IntRange(min=16, max=8192), default=640, show_default=True)
@click.option("--height", type=click.IntRange(min=12, max=8192), default=480, show_default=True)
@click.option("--camera", "camera_preset", type=click.Choice(["xtion", "mild", "ideal"]), default="xtion",
              show_default=True, help="Camera preset (CRF, vignetting, noise, auto exposure).")
@click.option("--vignetting-preset", type=click.Choice(["xtion", "mild", "none"]), default=None,
              help="Vignetting preset replacing the camera's.")
@click.option("--vignette-png", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="Use a DSO 16-bit vignette.png (resampled to the image size) as the vignetting.")
@click.option("--lensfun", "lensfun_lens", default=None, metavar="LENS",
              help="Use the vignetting of a lensfun lens (part of its name).")
@click.option("--lens-focal", type=Number(LENS_FOCAL_MM, "mm"), default=None, help="Focal length (mm) for --lensfun.")
@click.option("--lens-aperture", type=Number(LENS_APERTURE, "(f-number)"), default=None,
              help="Aperture (f-number) for --lensfun.")
@click.option("--lensfun-db", type=click.Path(exists=True, path_type=Path), default=None,
              help="lensfun database folder (default: $RADIOMAP_LENSFUN_DB or ../shared/data/lensfun/db).")
@click.option("--crf", default=None, metavar="FAMILY|FILE",
              help="Response: linear, gamma, s_curve, or a pcalib.txt / radiomap .npz response file.")
@click.option("--auto-exposure/--fixed-exposure", default=True, show_default=True,
              help="Room: auto exposure and white balance, or both fixed (metered on the first frame).")
@click.option("--exposure-time", type=Number(EXPOSURE_TIME_S, "s"), default=None, metavar="SECONDS",
              help="Exposure time in seconds (room: the start or fixed value; paper: the fixed value).")
@click.option("--light-change", type=Number(LIGHT_CHANGE, "x"), default=None,
              help="Room: the light switches to this factor of its brightness halfway through.")
@click.option("--flicker", type=Number(FLICKER, "", "a relative amplitude", open_max=True), default=0.0,
              show_default=True,
              help="Paper: relative amplitude of a smooth light flicker (recorded in truth).")
@click.option("--scene", "bracket_scene", type=click.Choice(["chart", "room"]), default="chart",
              show_default=True, help="Brackets: an HDR chart or a view of the room.")
@click.option("--jpeg-quality", type=click.IntRange(1, 100), default=None,
              help="Pass every frame through JPEG at this quality (frames are still written as PNG).")
@click.option("--supersample", type=click.IntRange(1, 4), default=1, show_default=True,
              help="Room: rays per pixel side (anti-aliasing; cost grows with its square).")
@click.option("--picture", "pictures", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              metavar="PATH", help="Room: hang this PNG/JPEG picture on a wall (longer side 0.5-1.0 m, aspect "
              "kept, sRGB decoded to linear albedo); repeat for several.")
@click.option("--force", is_flag=True, help="Overwrite a non-empty output folder (an earlier simulation there "
              "is removed first).")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@deprecated_alias("--frames", "num_frames", "--num-frames", "a count here; --frames is a range A:B:S elsewhere")
@deprecated_alias("--vignetting", "vignetting_preset", "--vignetting-preset",
                  "--vignetting is a model file elsewhere")
@deprecated_alias("--exposure", "exposure_time", "--exposure-time")
def command(kind: str, output: Path, seed: int, num_frames: int | None, width: int, height: int, camera_preset: str,
            vignetting_preset: str | None, vignette_png: Path | None, lensfun_lens: str | None,
            lens_focal: float | None, lens_aperture: float | None, lensfun_db: Path | None, crf: str | None,
            auto_exposure: bool, exposure_time: float | None, light_change: float | None, flicker: float,
            bracket_scene: str, jpeg_quality: int | None, supersample: int, pictures: tuple[Path, ...], force: bool,
            no_progress: bool) -> None:
    """Render a simulated sequence with ground truth: KIND is room (RGB-D, TUM layout), paper
    (white-paper vignetting sweep) or brackets (bracketed exposures)."""
    from radiometry.tables import format_table
    from mapping.simulation import sequences
    from radiometry.simulation import CameraSpec, VignettingSpec, crf_spec_from_file, find_lensfun_vignetting
    from radiometry.simulation import CRF_PRESETS, vignetting_preset as make_vignetting_preset

    n_sources = sum(v is not None for v in (vignetting_preset, vignette_png, lensfun_lens))
    if n_sources > 1:
        raise click.UsageError("give at most one of --vignetting-preset, --vignette-png and --lensfun")
    if kind != "room" and (light_change is not None or supersample != 1 or not auto_exposure or pictures):
        raise click.UsageError("--light-change, --supersample, --fixed-exposure and --picture are for 'room' "
                               "(paper and brackets always use a fixed exposure)")
    if kind != "paper" and flicker:
        raise click.UsageError("--flicker is for 'paper'")
    if kind == "brackets" and exposure_time is not None:
        raise click.UsageError("brackets use 1/1000 s doubling; --exposure-time is for room and paper")
    if (lens_focal is not None or lens_aperture is not None or lensfun_db is not None) and lensfun_lens is None:
        raise click.UsageError("--lens-focal, --lens-aperture and --lensfun-db need --lensfun LENS")

    try:
        spec = CameraSpec.preset(camera_preset, width=width, height=height)
        changes = {}
        if vignetting_preset is not None:
            changes["vignetting"] = make_vignetting_preset(vignetting_preset)
        elif vignette_png is not None:
            changes["vignetting"] = VignettingSpec.dso(vignette_png)
        elif lensfun_lens is not None:
            entry = find_lensfun_vignetting(lensfun_lens, focal=lens_focal, aperture=lens_aperture, db=lensfun_db)
            click.echo(f"vignetting: {entry.describe()} (corner {entry.corner():.2f})", err=True)
            changes["vignetting"] = VignettingSpec.lensfun(entry)
        if crf is not None:
            if crf in CRF_PRESETS:
                changes["crf"] = dict(CRF_PRESETS[crf])
            elif Path(crf).is_file():
                changes["crf"] = crf_spec_from_file(crf)
            else:
                raise click.BadParameter(f"{crf!r} is neither a response family ({', '.join(CRF_PRESETS)}) "
                                         "nor an existing pcalib.txt / .npz file", param_hint="--crf")
        if exposure_time is not None and kind == "room":
            changes["exposure_time"] = exposure_time
        if changes:
            changes["name"] = f"{camera_preset} (modified)"
            spec = spec.replace(**changes)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None

    n = num_frames if num_frames is not None else KIND_DEFAULT_FRAMES[kind]
    progress = not no_progress
    t0 = time.perf_counter()
    if kind == "room":
        light = None if light_change is None else sequences.light_step(n, light_change)
        out = sequences.simulate_room(output, camera=spec, seed=seed, n_frames=n, auto_exposure=auto_exposure,
                                      exposure_time=exposure_time, light_scale=light, jpeg_quality=jpeg_quality,
                                      supersample=supersample, pictures=pictures, force=force,
                                      progress=progress)
    elif kind == "paper":
        out = sequences.simulate_paper(output, camera=spec, seed=seed, n_frames=n, exposure_time=exposure_time,
                                       flicker=flicker, jpeg_quality=jpeg_quality, force=force, progress=progress)
    else:
        if n < 2:
            raise click.BadParameter("brackets need at least 2 exposures", param_hint="--num-frames")
        out = sequences.simulate_brackets(output, camera=spec, seed=seed, n_exposures=n, scene=bracket_scene,
                                          jpeg_quality=jpeg_quality, force=force, progress=progress)
    elapsed = time.perf_counter() - t0
    row = {"kind": kind, "frames": n, "size": f"{width}x{height}", "camera": spec.name,
           "vignetting": spec.vignetting.source or spec.vignetting.kind, "crf": spec.crf["family"],
           "seed": seed, "seconds": round(elapsed, 1), "output": str(out)}
    click.echo(format_table([row]))
    from mapping.cli._common import written_text

    click.echo(written_text(Path(out)), err=True)
