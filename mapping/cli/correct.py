"""``radiomap correct``: remove vignetting (through the response) from images or a video."""

from __future__ import annotations

import contextlib
import json
import os
import re
from pathlib import Path

import click

from mapping.cli._common import RadiomapCommand, deprecated_alias

EPILOG = """\b
Examples:
  radiomap correct frames/ --response crf.npz --vignetting vignetting.npz -o corrected/
  radiomap correct clip.mp4 -r crf.npz --vignetting xtion.vgn -o corrected/ --scale 0.8
      (--scale < 1 darkens the result so that bright corners do not clip; --scale auto picks the
       scale that keeps 99.5% of the first frames' pixels unclipped)
  radiomap correct frame.png -r pcalib.txt --vignetting vignette.png -o irr/ --irradiance --irradiance-format tiff
      (32-bit float irradiance f^-1(I)/V, RGB, for fusion or measurement)
"""


#: correct's record of the outputs it wrote into its folder: the next ``--force`` run removes those it does not rewrite
RECORD = ".radiomap-correct.json"
#: the names of a video's frames: what a radiomap before the record left, recognised without it
_FRAME_NAME = re.compile(r"frame_\d{6}\.(png|npy|tiff|exr)\Z")


def _earlier_outputs(out: Path, *, video: bool) -> list[str]:
    """The outputs an earlier ``correct`` wrote into ``out`` that are still there: those its record lists or, with no
    record (a radiomap before it) and a video to correct now, the files named like a video's frames. Any other file
    in ``out`` is the user's: never listed."""
    try:
        listed = json.loads((out / RECORD).read_text()).get("files", [])
        names = {n for n in listed if isinstance(n, str) and n not in ("", ".", "..", RECORD) and n == Path(n).name}
    except FileNotFoundError:
        names = {p.name for p in out.iterdir() if _FRAME_NAME.match(p.name)} if video else set()
    except (OSError, ValueError, AttributeError):   # unreadable: nothing is known to be correct's
        names = set()
    return sorted(n for n in names if (out / n).is_file())


def _is_one_of(path: Path, others) -> bool:
    for other in others:
        with contextlib.suppress(OSError):
            if os.path.samefile(path, other):
                return True
    return False


def _folder_frames(paths, irradiance: bool):
    """The images: 16-bit ones at full precision for ``--irradiance`` (``f^-1`` interpolated between its 256 levels
    at ``value / 257``), reduced to their top 8 bits for 8-bit output, said once."""
    import numpy as np

    from radiometry.images import read_rgb

    said = False
    for path in paths:
        image = read_rgb(path, keep_16bit=True)
        if image.dtype == np.uint16 and not irradiance:
            if not said:
                said = True
                click.echo(f"note: {path} is a 16-bit image: its 8-bit output is corrected from its top 8 bits (as "
                           "every 16-bit input); --irradiance uses all 16", err=True)
            image = (image >> 8).astype(np.uint8)
        yield image


def _scale_type(value: str) -> float | str:
    if value.strip().lower() == "auto":
        return "auto"
    try:
        number = float(value)
    except ValueError:
        raise click.BadParameter(f"{value!r} is neither a number nor 'auto'") from None
    from mapping.validation import check_exposure_factor

    return check_exposure_factor(number, "--scale")  # 1e-4..1e4 (mapping/validation.py)


@contextlib.contextmanager
def _models_must_fit(what, response_path: str, vignetting_path: str):
    """Name the image and both model files when the models do not fit an image (size, aspect, channels)."""
    from radiometry.errors import ModelMismatchError

    try:
        yield
    except ModelMismatchError as exc:
        raise ModelMismatchError(f"{what} does not fit the models ({response_path}, {vignetting_path}): {exc}") \
            from None


@click.command("correct", cls=RadiomapCommand, epilog=EPILOG)
@click.argument("input_path", metavar="INPUT", type=click.Path(exists=True))
@click.option("-r", "--response", "response_path", required=True, type=click.Path(dir_okay=False),
              help="Camera response: radiomap .npz, radical .crf or DSO pcalib.txt.")
@click.option("--vignetting", "vignetting_path", required=True, type=click.Path(dir_okay=False),
              help="Vignetting model: radiomap .npz, radical .vgn, DSO vignette.png, or a V array .npy.")
@click.option("-o", "--output", "outdir", required=True, type=click.Path(file_okay=False),
              help="Output folder.")
@click.option("--scale", default="1.0", show_default=True, type=str,
              help="Brightness factor of the uint8 output (< 1 avoids clipping at the corners), or 'auto'.")
@click.option("--irradiance", is_flag=True, help="Write float irradiance f^-1(I)/V instead of 8-bit images.")
@click.option("--irradiance-format", "fmt", type=click.Choice(["npy", "tiff", "exr"]), default="npy",
              show_default=True, help="File format of --irradiance output.")
@click.option("--stderr", "stderr_path", type=click.Path(dir_okay=False), default=None,
              help="Also write the per-pixel relative standard error of the corrected irradiance that comes from "
                   "the vignetting calibration (.npy, .tiff or .exr; float32 HxWxC at the images' size). Needs a "
                   "LUT calibrated by radiomap vignetting.")
@click.option("--force", is_flag=True, help="Replace an earlier run's outputs as a whole: those this run does not "
              "rewrite (the last frames of a longer video) are removed; other files are kept.")
@click.option("--no-progress", is_flag=True, help="No progress bar.")
@deprecated_alias("-v", "vignetting_path", "--vignetting", "-v is radiomap's --verbose: radiomap -v correct ...")
@deprecated_alias("--format", "fmt", "--irradiance-format", "--format is a sequence layout elsewhere")
def command(input_path: str, response_path: str, vignetting_path: str, outdir: str, scale: str,
            irradiance: bool, fmt: str, stderr_path: str | None, force: bool, no_progress: bool) -> None:
    """Correct INPUT (an image, a folder of images or a video): I' = f(scale * f^-1(I) / V(x)).

    8-bit results are written as PNG (lossless), one per input image or video frame.
    """
    import itertools

    import numpy as np

    from radiometry.api import read_vignetting
    from radiometry.correction import Corrector
    from radiometry.errors import OutputError
    from radiometry.fileio import atomic_write_json, check_outputs, check_overwrite, ensure_dir, publish_set
    from radiometry.formats import load_response
    from radiometry.images import ORIENTATIONS, check_float_format, exif_orientation, write_float_image, write_image
    from radiometry.progress import progress_bar
    from radiometry.vignetting_calibration import FolderFrames, VideoFrames, open_frames

    try:
        scale_value = _scale_type(scale)
    except click.BadParameter as exc:
        raise click.BadParameter(str(exc), param_hint="--scale") from None
    response = load_response(response_path)
    vignetting = read_vignetting(vignetting_path)  # as reconstruct --vignetting: also a V array .npy
    corrector = Corrector(response, vignetting)
    if stderr_path is not None:
        if Path(stderr_path).suffix.lower() not in (".npy", ".tiff", ".tif", ".exr"):
            raise click.BadParameter(f"{stderr_path}: write the standard error as .npy, .tiff or .exr",
                                     param_hint="--stderr")
        if getattr(vignetting, "stderr", None) is None:
            raise click.BadParameter(f"{vignetting_path} carries no standard error (only a LUT calibrated by "
                                     "radiomap vignetting into .npz does); drop --stderr or re-calibrate",
                                     param_hint="--stderr")
        check_overwrite(stderr_path, force=force)
        check_float_format(stderr_path)  # before any image is written
    source = open_frames(input_path)
    if isinstance(source, FolderFrames):
        names = [p.stem for p in source.paths]
    else:
        names = None
    ext = {"npy": ".npy", "tiff": ".tiff", "exr": ".exr"}[fmt] if irradiance else ".png"
    if names is not None:  # refuse before writing anything rather than half-way through
        pairs = [(path, Path(outdir) / f"{name}{ext}") for path, name in zip(source.paths, names)]
        check_outputs(pairs, fix_input="choose another output folder (-o); --force never replaces an input",
                      fix_shared="correct such images into separate output folders (or rename one)")
        for _path, target in pairs:
            check_overwrite(target, force=force)
    if irradiance:  # an OpenCV without OpenEXR: say so before the output folder is made
        try:
            check_float_format(Path(outdir) / f"irradiance{ext}")
        except OutputError:
            raise click.BadParameter(f"this OpenCV build cannot write 32-bit float {fmt.upper()} images; use npy or "
                                     "tiff", param_hint="--irradiance-format") from None
    out = ensure_dir(outdir)
    earlier = _earlier_outputs(out, video=isinstance(source, VideoFrames))
    this_run: list[str] = []   # the names this run writes into out
    retired: list[str] = []

    frames = iter(source) if names is None else _folder_frames(source.paths, irradiance)
    if scale_value == "auto" and not irradiance:
        head = list(itertools.islice(frames, 10))
        with _models_must_fit(input_path, response_path, vignetting_path):
            scale_value = corrector.suggest_scale(head, percentile=99.5) if head else 1.0
        frames = itertools.chain(head, frames)
        click.echo(f"--scale auto: {scale_value:.4f} keeps 99.5% of the first {len(head)} frames unclipped")
    elif scale_value == "auto":
        scale_value = 1.0
    written = 0
    clipped = 0
    total = 0
    bar = progress_bar(frames, total=source.length, desc="correct", enabled=not no_progress, leave=False)
    first_shape = None
    resampled: set[tuple[int, int]] = set()   # the image sizes the model was said to be resampled to
    turned = False   # an input's EXIF orientation was said
    se = None
    # all outputs or none: written to a staging folder and renamed into place once every frame is done, so an error
    # or Ctrl-C/SIGTERM half-way leaves the folder as it was (no partial set, no earlier output half-replaced)
    with publish_set() as files:
        for i, frame in enumerate(bar):
            shape = np.asarray(frame).shape[:2]
            if first_shape is None:
                first_shape = shape
            name = names[i] if names is not None else (f"frame_{i:06d}" if isinstance(source, VideoFrames)
                                                       else Path(input_path).stem)
            target = out / f"{name}{ext}"
            check_overwrite(target, force=force)
            source_name = source.paths[i] if names is not None else f"{input_path} ({name})"
            # the pixels as stored (the sensor's order, where V lives); the PNG keeps the photo's orientation tag
            orientation = exif_orientation(source.paths[i]) if names is not None else 1
            if orientation != 1 and not turned:
                turned = True
                click.echo(f"note: {source_name} declares EXIF orientation {orientation} (viewers show it "
                           f"{ORIENTATIONS[orientation]}): corrected in its stored (sensor) pixel order, as the vignetting "
                           "is; " + (f"the {ext} irradiance maps carry no orientation: rotate them for display" if
                                     irradiance else "the PNG carries the same orientation, so viewers turn it alike"),
                           err=True)
            if irradiance:
                with _models_must_fit(source_name, response_path, vignetting_path):
                    irr = corrector.irradiance(frame)
                write_float_image(files.path(target), irr)
            else:
                with _models_must_fit(source_name, response_path, vignetting_path):
                    result = corrector.correct(frame, scale=float(scale_value))
                clipped += int(np.count_nonzero((result == 255) & (np.asarray(frame) < 255)))
                total += result.size
                write_image(files.path(target), result, orientation=orientation)
            written += 1
            this_run.append(target.name)
            model_size = tuple(getattr(vignetting, "resolution", shape[::-1]))
            if model_size != shape[::-1] and shape not in resampled:  # said once it fitted (same aspect)
                resampled.add(shape)   # said once per size, for every size that needs it (a mixed-size folder)
                click.echo(f"note: the vignetting model ({model_size[0]}x{model_size[1]}) is resampled to the "
                           f"images' {shape[1]}x{shape[0]} ({source_name}"
                           f"{' and any other of that size' if names is not None and len(names) > 1 else ''}): right "
                           "when they cover the same sensor area (binned or scaled), wrong for a cropped sensor mode",
                           err=True)
        if stderr_path is not None and first_shape is not None:
            from radiometry.correction import corrected_relative_stderr

            with _models_must_fit(input_path, response_path, vignetting_path):
                se = corrected_relative_stderr(vignetting, first_shape[0], first_shape[1])
            write_float_image(files.path(ensure_dir(Path(stderr_path).parent) / Path(stderr_path).name), se)
            if os.path.abspath(Path(stderr_path).parent) == os.path.abspath(out):
                this_run.append(Path(stderr_path).name)
        if written:
            # --force: the folder holds this run's outputs only, the earlier run's that it did not rewrite (the last
            # frames of a longer video) removed in the same commit (kept if the run fails or is interrupted);
            # without it nothing was replaced, and the earlier outputs stay listed
            inputs = [*(source.paths if names is not None else [input_path]), response_path, vignetting_path]
            retired = [n for n in earlier if n not in this_run and not _is_one_of(out / n, inputs)] if force else []
            for stale in retired:
                files.retire(out / stale)
            listed = sorted(set(this_run) | (set() if force else set(earlier)))
            atomic_write_json(files.path(out / RECORD), {"written_by": "radiomap correct", "input": str(input_path),
                                                        "files": listed})
    if retired:
        click.echo(f"removed {len(retired)} output{'s' if len(retired) > 1 else ''} of the earlier run that this one did "
                   f"not rewrite ({retired[0]}{' .. ' + retired[-1] if len(retired) > 1 else ''})")
    if se is not None:
        click.echo(f"wrote the relative standard error of the corrected irradiance to {stderr_path} (median "
                   f"{100 * float(np.median(se)):.2f}%, 99th percentile {100 * float(np.percentile(se, 99)):.2f}%)")
    kind = "irradiance maps" if irradiance else "corrected images"
    click.echo(f"wrote {written} {kind} to {out}" + ("" if irradiance else
               f" (scale {float(scale_value):.4g}; {100.0 * clipped / max(total, 1):.2f}% of values newly clipped"
               + ("; lower --scale to avoid it)" if clipped else ")")))
