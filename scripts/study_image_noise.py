#!/usr/bin/env python3
"""Study: the noise the truth-free quality figure compares with (radiometry/response/noise.py), against the truth.

Stacks come from ``tests/camera_pipelines.py`` (independent of radiometry): gamma 2.2, twelve 2x exposures, 320x240,
over ``tests/response_curves.py``'s smooth scene (a log gradient, flat patches) or a random-pixel texture (each pixel's
radiance log-uniform over 10 stops, independent per pixel and channel), with Gaussian noise of a known spread after
the response (no photon noise) or the default sensor (photon and read noise). The truth is measured independently: the
same stack rendered again with other noise draws; the standard deviation of ``z1 - z2`` over ``sqrt 2``, over the pixels
within levels 3..252 of both, mean over channels, RMS over exposures (an RMS: where the noise varies with the level,
photon noise, it is above the robust figures, which read a typical pixel).

Per stack: the truth, the Laplacian's figure (in one image), the figure between exposures, which one the quality
figure uses, and the grade of the right curve and of a wrong one (gamma 2.0 given for the gamma 2.2 camera; the kink
curve) with the noise used now and with the Laplacian's alone (the grading before 2026-11-28). ``--real`` adds the
bracket stacks of ``../shared/data/brackets`` (the response fitted, ``--quality fast``'s figure).

``--pipelines`` adds the right curve through every pipeline of ``tests/camera_pipelines.py`` (every curve on the smooth
scene, gamma 2.2 and EuRoC on random pixels too): a right curve must never be graded broken.

Usage::

    python scripts/study_image_noise.py [--real] [--pipelines] [--size 320x240]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for path in (REPO, REPO / "tests"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

TIMES = 2.0 ** np.arange(-11, 1)
#: no photon noise: only the Gaussian noise after the response (and the rounding) is the truth
NO_SENSOR_NOISE = {"full_well": 1e12, "read_noise": 0.0}


def texture(height: int, width: int, seed: int) -> np.ndarray:
    """Random pixels: radiance log-uniform over 2^-10 .. 1 (x 2^5), independent per pixel and channel."""
    rng = np.random.default_rng(seed)
    return np.exp(rng.uniform(math.log(2.0 ** -5), math.log(2.0 ** 5), (height, width, 3)))


def truth(table, radiance, pipeline: dict) -> float:
    """The noise measured from two renders of the same stack with other noise draws (module docstring)."""
    from camera_pipelines import render

    a = np.stack(render(table, radiance, TIMES, seed=2, **pipeline)).astype(np.float64)
    b = np.stack(render(table, radiance, TIMES, seed=12, **pipeline)).astype(np.float64)
    per = []
    for k in range(len(TIMES)):
        ch = []
        for c in range(3):
            sel = (a[k, ..., c] >= 3) & (a[k, ..., c] <= 252) & (b[k, ..., c] >= 3) & (b[k, ..., c] <= 252)
            if sel.sum() >= 100:
                ch.append(float(np.std(a[k, ..., c][sel] - b[k, ..., c][sel])) / math.sqrt(2.0))
        if ch:
            per.append(float(np.mean(ch)))
    return math.sqrt(float(np.mean(np.square(per))))


def grades(images, times, response) -> tuple[dict, str, str]:
    """The quality record, its grade and the grade the Laplacian's figure alone gave (the code before: the same where
    no texture is flagged; where it is, the verdict over the Laplacian's figure, which is what the code before gave for
    a response with no tied levels on a stack not called JPEG, the only stacks flagged)."""
    from radiometry.response.quality import MERGE_FACTOR, assess, verdict

    q = assess(images, times, response)
    before = q["grade"]
    if q["image_noise_levels"] is None:
        ratio = q["holdout_rms_levels"] / (MERGE_FACTOR * q["laplacian_noise_levels"])
        before = verdict(q["holdout_rms_levels"], None, ratio, compressed=q["jpeg"])[0]
    return q, f"{q['holdout_over_noise']:.2f}x {q['grade']}", before


def row(name: str, images, times, table, true_noise: float | None) -> dict:
    from radiometry.response import CameraResponse
    from response_curves import curves

    right, _, right_before = grades(images, times, CameraResponse.from_table(table))
    wrong = {}
    for label, response in (("gamma 2.0", CameraResponse.gamma(2.0, 3)),
                            ("kink", CameraResponse.from_table(curves()["kink-4x"]))):
        q, now, before = grades(images, times, response)
        wrong[label] = f"{q['holdout_rms_levels']:.2f}: {before} -> {now}"
    return {"stack": name, "truth": "" if true_noise is None else f"{true_noise:.2f}",
            "Laplacian": f"{right['laplacian_noise_levels']:.2f}",
            "between": f"{right['noise_between_exposures_levels']:.2f}",
            "used": right["noise_measured"].split(" (")[0],
            "right curve: RMS, grade before -> now": f"{right['holdout_rms_levels']:.2f}: {right_before} -> "
                                                      f"{right['holdout_over_noise']:.2f}x {right['grade']}",
            "gamma 2.0 given": wrong["gamma 2.0"], "kink given": wrong["kink"]}


def synthetic_rows(size: tuple[int, int]) -> list[dict]:
    from camera_pipelines import render
    from response_curves import curves, scene

    width, height = size
    table = curves()["gamma-2.2"]
    scenes = {"smooth": scene(height, width, seed=1), "random pixels": texture(height, width, seed=4)}
    rows = []
    for scene_name, radiance in scenes.items():
        cases = [(f"noise {s:g} after the response", {"post_noise": s, **NO_SENSOR_NOISE}) for s in (0.5, 1.0, 2.0)]
        cases += [("photon and read noise", {}), ("photon and read noise, JPEG q92", {"quality": 92})]
        for label, pipeline in cases:
            images = render(table, radiance, TIMES, seed=2, **pipeline)
            rows.append(row(f"{scene_name}, {label}", images, TIMES, table, truth(table, radiance, pipeline)))
        rng = np.random.default_rng(3)
        images = render(table, radiance, TIMES, seed=2, post_noise=1.0, **NO_SENSOR_NOISE)
        moved = [np.roll(im, tuple(rng.integers(-2, 3, 2)), axis=(0, 1)) for im in images]
        rows.append(row(f"{scene_name}, noise 1, camera moved 1-2 px", moved, TIMES, table, None))
    return rows


def pipeline_rows(size: tuple[int, int]) -> list[dict]:
    """The right curve through every pipeline of tests/camera_pipelines.py, per curve, on the smooth scene and on random
    pixels: which noise is used and the grade before and now (a right curve must never be broken)."""
    from camera_pipelines import PIPELINES, render
    from radiometry.response import CameraResponse
    from response_curves import curves, scene

    width, height = size
    scenes = {"smooth": scene(height, width, seed=1), "random pixels": texture(height, width, seed=4)}
    rows = []
    for curve, table in curves().items():
        for pipeline, options in PIPELINES.items():
            for scene_name, radiance in scenes.items():
                if scene_name != "smooth" and curve not in ("gamma-2.2", "euroc"):
                    continue
                images = render(table, radiance, TIMES, seed=2, **options)
                q, now, before = grades(images, TIMES, CameraResponse.from_table(table))
                rows.append({"curve": curve, "pipeline": pipeline, "scene": scene_name, "JPEG found": q["jpeg"],
                             "Laplacian": f"{q['laplacian_noise_levels']:.2f}",
                             "between": f"{q['noise_between_exposures_levels']:.2f}",
                             "used": q["noise_measured"].split(" (")[0],
                             "held-out RMS": f"{q['holdout_rms_levels']:.2f}", "before -> now": f"{before} -> {now}"})
    return rows


def real_rows() -> list[dict]:
    from radiometry.response.fit import fit_response, load_brackets
    from radiometry.response.quality import assess

    rows = []
    data = REPO.parent / "shared" / "data" / "brackets"
    for name, mask_blue in (("taipei", False), ("memorial_debevec1997", True)):
        if not (data / name).is_dir():
            print(f"{data / name} is absent: skipped", file=sys.stderr)
            continue
        images, times, _ = load_brackets(data / name, progress=False)
        mask = None
        if mask_blue:
            from radiometry.response.fit import blue_fill_mask

            mask = blue_fill_mask(images)
        response = fit_response(images, times, **({"mask": mask} if mask is not None else {}))
        q = assess(images, times, response, mask=mask, fitted=True)
        rows.append({"stack": name, "Laplacian": f"{q['laplacian_noise_levels']:.2f}",
                     "between": f"{q['noise_between_exposures_levels']:.2f}",
                     "used": q["noise_measured"].split(" (")[0],
                     "held-out RMS (fast)": f"{q['holdout_rms_levels']:.2f}",
                     "x noise": f"{q['holdout_over_noise']:.2f}", "grade": q["grade"]})
    return rows


def table(rows: list[dict]) -> str:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(str(r.get(k, "")) for k in keys) + " |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="320x240", help="image size WxH (default 320x240)")
    parser.add_argument("--real", action="store_true", help="also the real bracket stacks of ../shared/data")
    parser.add_argument("--no-synthetic", action="store_true", help="only the real stacks")
    parser.add_argument("--pipelines", action="store_true",
                        help="also the right curve through every camera pipeline (curves x pipelines x scenes)")
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    if not args.no_synthetic:
        print(table(synthetic_rows(size)))
    if args.pipelines:
        print()
        print(table(pipeline_rows(size)))
    if args.real or args.no_synthetic:
        print()
        print(table(real_rows()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
