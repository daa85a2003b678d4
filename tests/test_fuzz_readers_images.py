"""Fuzzing of the image readers (colour and depth frames, DSO vignette.png) and of the bracket folders'
exposure-time lists (times.txt, load_brackets).

Random and mutated inputs must raise only radiomap's own errors; see ``fuzz_helpers`` for the method.
"""

from __future__ import annotations

import math
import random
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given

from fuzz_helpers import (
    H, SEEDS, W, check_vignetting, fuzz, grammar_text, mutate_bytes, mutate_text, only_own_errors, put, random_input,
    seeds)
from fuzz_helpers import fuzz_watchdog, workdir  # noqa: F401 (pytest fixtures: the watchdog, a scratch folder)


# ==================================================================================================
# DSO vignette.png and the image readers (colour, depth)
# ==================================================================================================
def png_image(rng: random.Random) -> bytes:
    """A valid PNG of any kind: 8/16 bit, 1/3/4 channels, tiny or wide, zero, saturated or noisy."""
    dtype = rng.choice([np.uint8, np.uint16])
    shape = rng.choice([(H, W), (H, W, 1), (H, W, 3), (H, W, 4), (1, 1), (1, 300), (300, 1)])
    top = int(np.iinfo(dtype).max)
    fill = rng.choice(["zeros", "max", "noise", "one_zero"])
    gen = np.random.default_rng(rng.randrange(2**32))
    img = {"zeros": np.zeros(shape, dtype), "max": np.full(shape, top, dtype)}.get(fill)
    if img is None:
        img = gen.integers(1, top, size=shape, endpoint=True).astype(dtype)
        if fill == "one_zero":
            img.reshape(-1)[0] = 0
    return cv2.imencode(".png", img)[1].tobytes()


def png_size_lie(seed: bytes, rng: random.Random) -> bytes:
    """Rewrite the IHDR width and/or height: a corrupt size must not make a reader allocate or scan for
    seconds."""
    data = bytearray(seed)
    for offset in rng.sample([16, 20], rng.randint(1, 2)):
        data[offset:offset + 4] = struct.pack(">I", rng.choice([0, 1, 2**31 - 1, 2**31, 2**32 - 1, 100000, 30000,
                                                                65535, 16384]))
    return bytes(data)


def jpeg_size_lie(seed: bytes, rng: random.Random) -> bytes:
    """Rewrite the height and/or width of a JPEG's start-of-frame segment (e.g. 65535 x 65535)."""
    data = bytearray(seed)
    sof = data.find(b"\xff\xc0")
    for offset in rng.sample([5, 7], rng.randint(1, 2)):
        data[sof + offset:sof + offset + 2] = struct.pack(">H", rng.choice([0, 1, 65535, 65500, 30000, 16384]))
    return bytes(data)


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_dso_vignette_png(workdir, seed):
    from radiometry.formats.dso_vignette import read_dso_vignette

    rng = random.Random(seed)
    which = rng.random()
    if which < 0.45:
        data = mutate_bytes(seeds()["vignette.png"], rng, header=48)
    elif which < 0.6:
        data = png_size_lie(seeds()["vignette.png"], rng)
    elif which < 0.85:
        data = png_image(rng)
    else:
        data = random_input(rng)
    check_vignetting(only_own_errors(read_dso_vignette, put(workdir, "vignette.png", data)))


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_colour_and_depth_images(workdir, seed):
    from radiometry.images import read_depth, read_rgb

    rng = random.Random(seed)
    which = rng.random()
    name = "frame.png"
    if which < 0.4:
        data = mutate_bytes(seeds()[rng.choice(["rgb.png", "depth.png"])], rng, header=48)
    elif which < 0.55:
        data = png_size_lie(seeds()[rng.choice(["rgb.png", "depth.png"])], rng)
    elif which < 0.65:
        data, name = mutate_bytes(seeds()["rgb.jpg"], rng, header=200), "frame.jpg"
    elif which < 0.75:
        data, name = jpeg_size_lie(seeds()["rgb.jpg"], rng), "frame.jpg"
    elif which < 0.9:
        data = png_image(rng)
    else:
        data = random_input(rng)
    path = put(workdir, name, data)
    rgb = only_own_errors(read_rgb, path)
    if rgb is not None:
        assert rgb.dtype == np.uint8 and (rgb.ndim == 2 or rgb.shape[2] == 3)
    depth = only_own_errors(read_depth, path, 1000.0)
    if depth is not None:
        assert depth.dtype == np.float32 and depth.ndim == 2 and np.all(np.isfinite(depth)) and np.all(depth >= 0)


# ==================================================================================================
# exposure-time lists (bracket folders)
# ==================================================================================================
TIMES = "# name seconds\nexposure_0.png 0.001\nexposure_1.png 1/250\nexposure_2.png 0.016 62.5\n"


def times_input(rng: random.Random) -> bytes | str:
    which = rng.random()
    if which < 0.6:
        return mutate_text(TIMES, rng)
    if which < 0.85:
        text = grammar_text(rng, [2, 3], max_rows=6)
        return "\n".join(f"exposure_{i}.png {line}" if rng.random() < 0.7 else line
                         for i, line in enumerate(text.splitlines())) + "\n"
    return random_input(rng, text=True)


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_times_file(workdir, seed):
    from radiometry.response.fit import read_times_file

    entries = only_own_errors(read_times_file, put(workdir, "times.txt", times_input(random.Random(seed))))
    if entries is not None:
        assert entries and all(math.isfinite(t) and t > 0 for _, t in entries)
        assert len({n for n, _ in entries}) == len(entries)


@pytest.fixture(scope="module")
def bracket_folder(workdir) -> Path:
    folder = workdir / "brackets"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"exposure_{i}.png"), np.full((6, 8, 3), 40 * (i + 1), np.uint8))
    return folder


@pytest.mark.slow
@fuzz(2000)
@given(seed=SEEDS)
def test_bracket_folder_with_mutated_times(bracket_folder, seed):
    """load_brackets (what 'radiomap response' reads): the times file against the folder's images."""
    from radiometry.response.fit import load_brackets

    put(bracket_folder, "times.txt", times_input(random.Random(seed)))
    result = only_own_errors(load_brackets, bracket_folder)
    if result is not None:
        images, times, names = result
        assert len(images) == len(times) == len(names) == 3 and np.all(times > 0)
