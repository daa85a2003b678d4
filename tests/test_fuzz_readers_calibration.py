"""Fuzzing of the calibration-file readers: radiomap model archives (.npz: response, vignetting, vignetting
accumulation), radical .crf and .vgn, DSO pcalib.txt, and the --response / --vignetting dispatchers.

Random and mutated inputs must raise only radiomap's own errors; see ``fuzz_helpers`` for the method.
"""

from __future__ import annotations

import io
import json
import math
import random
import struct
import zipfile

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzz_helpers import (
    H, INTERESTING_FLOATS, SEEDS, W, check_response, check_vignetting, encode, fuzz, hostile_json, hostile_token,
    mutate_bytes, mutate_text, only_own_errors, put, random_input, seeds)
from fuzz_helpers import fuzz_watchdog, workdir  # noqa: F401 (pytest fixtures: the watchdog, a scratch folder)


# ==================================================================================================
# radiomap model files (.npz): response, vignetting (LUT, polynomial), vignetting accumulation
# ==================================================================================================
def _mutate_array(a: np.ndarray, rng: random.Random) -> np.ndarray:
    op = rng.choice(["values", "values", "shape", "dtype", "random"])
    if op == "values" and a.size:
        a = np.array(a, dtype=np.float64 if a.dtype.kind in "fc" else a.dtype, copy=True)
        flat = a.reshape(-1)
        for _ in range(rng.randint(1, 5)):
            v = rng.choice(INTERESTING_FLOATS)
            if a.dtype.kind == "f":
                flat[rng.randrange(flat.size)] = v
            elif math.isfinite(v):
                info = np.iinfo(a.dtype) if a.dtype.kind in "iu" else None
                flat[rng.randrange(flat.size)] = (bool(v) if info is None else info.max if v >= info.max
                                                  else info.min if v <= info.min else int(v))
        if rng.random() < 0.2:
            a = a[::-1].copy()  # a decreasing table, a mirrored LUT
        return a
    if op == "shape":
        shape = rng.choice([(256,), (256, 1), (256, 2), (255, 3), (257, 3), (0,), (), (3, 256), (W, H, 3), (H, W),
                            (H, W, 1), (H, W, 2), (H, W, 4), (H, W + 1, 3), (1, 3), (3, 3), (3, 2), (2,), (3,),
                            (1, 1, 1, 1), (2, H, W, 3), (0, 4, 5, 3)])
        return np.resize(a, shape) if a.size else np.zeros(shape)
    if op == "dtype":
        dtype = rng.choice(["<f4", "<f8", "<i4", "<u1", "?", "<c8", "<U4", "S3", "<M8[s]", "<f2", ">f8"])
        with np.errstate(all="ignore"):
            try:
                return a.astype(dtype)
            except (ValueError, TypeError, OverflowError):
                return np.zeros(a.shape, dtype=dtype)
    shape = tuple(rng.randint(0, 5) for _ in range(rng.randint(0, 4)))
    return np.array([rng.choice(INTERESTING_FLOATS + [0.5, 0.9, 1.0]) for _ in range(int(np.prod(shape)))],
                    dtype=rng.choice([np.float64, np.float32])).reshape(shape)


def _mutate_meta(meta: dict, rng: random.Random) -> str:
    meta = json.loads(json.dumps(meta))
    keys = ["format", "kind", "version", "model", "resolution", "channels", "info", "block", "skipped", "source"]
    for _ in range(rng.randint(1, 4)):
        key = rng.choice(keys)
        op = rng.choice(["set", "set", "delete", "numbers"])
        if op == "delete":
            meta.pop(key, None)
        elif op == "numbers" and isinstance(meta.get(key), list):
            meta[key] = [rng.choice([*INTERESTING_FLOATS, 0, -5, 10**6, 10**30, -(10**30), 10**400]) for _ in meta[key]]
        else:
            meta[key] = hostile_json(rng)
    text = json.dumps(meta, allow_nan=True)
    if rng.random() < 0.05:  # hostile documents: deep nesting, truncation, not an object
        text = rng.choice(["[" * 100_000 + "]" * 100_000, '{"a":' * 50_000 + "1" + "}" * 50_000, text[: len(text) // 2],
                           "", "null", "[]", '"radiomap"'])
    return text


def model_archive(seed: bytes, rng: random.Random) -> bytes:
    """A valid model archive with its meta and arrays mutated (values, shapes, dtypes, missing entries),
    re-packed as a well-formed .npz so that the reader's checks (not the zip layer) are exercised."""
    with np.load(io.BytesIO(seed), allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays.pop("meta")))
    for name in list(arrays):
        op = rng.choice(["keep", "keep", "mutate", "drop"])
        if op == "mutate":
            arrays[name] = _mutate_array(arrays[name], rng)
        elif op == "drop":
            del arrays[name]
    if rng.random() < 0.1:
        arrays[rng.choice(["extra", "inverse_table", "lut", "scale"])] = _mutate_array(np.ones(3), rng)
    meta_text = _mutate_meta(meta, rng) if rng.random() < 0.6 else json.dumps(meta)
    if rng.random() < 0.95:
        arrays["meta"] = np.array(meta_text) if rng.random() < 0.95 else _mutate_array(np.ones(2), rng)
    buf = io.BytesIO()
    (np.savez if rng.random() < 0.5 else np.savez_compressed)(buf, **arrays)
    return buf.getvalue()


def foreign_zip(rng: random.Random) -> bytes:
    """A zip file that is not a numpy archive, or whose members lie (e.g. a .npy header claiming 745 GiB)."""
    buf = io.BytesIO()
    method = rng.choice([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA])
    header = (b"\x93NUMPY\x01\x00v\x00{'descr': '<f8', 'fortran_order': False, 'shape': (99999999999,), }"
              + b" " * 50 + b"\n")
    with zipfile.ZipFile(buf, "w", compression=method) as z:
        for i in range(rng.randint(0, 3)):
            name = rng.choice(["meta.npy", "inverse_table.npy", "lut.npy", "x.txt", "meta", "../evil.npy"])
            body = rng.choice([rng.randbytes(rng.randint(0, 200)), header, header[:rng.randint(0, len(header))]])
            z.writestr(f"{i}/{name}" if name.startswith("..") else name, body)
    return buf.getvalue()


def _npz_input(kind: str, rng: random.Random) -> bytes:
    names = {"response": ["r.npz", "r1.npz"], "vignetting": ["lut.npz", "poly.npz"], "acc": ["acc.npz"]}[kind]
    seed = seeds()[rng.choice(names)]
    which = rng.random()
    if which < 0.55:
        return model_archive(seed, rng)
    if which < 0.85:
        return mutate_bytes(seed, rng, header=rng.choice([64, 600]))
    return foreign_zip(rng) if rng.random() < 0.5 else random_input(rng)


@pytest.mark.slow
@fuzz(2500)
@given(seed=SEEDS)
def test_response_npz(workdir, seed):
    from radiometry.response import CameraResponse

    data = _npz_input("response", random.Random(seed))
    check_response(only_own_errors(CameraResponse.load, put(workdir, "r.npz", data)))


@pytest.mark.slow
@fuzz(2500)
@given(seed=SEEDS)
def test_vignetting_npz(workdir, seed):
    from radiometry.vignetting import VignettingModel

    data = _npz_input("vignetting", random.Random(seed))
    check_vignetting(only_own_errors(VignettingModel.load, put(workdir, "v.npz", data)))


@pytest.mark.slow
@fuzz(2000)
@given(seed=SEEDS)
def test_vignetting_accumulation_npz(workdir, seed):
    """Accumulations saved with --save-accumulation: a file that loads can be fitted (or fails cleanly)."""
    from radiometry.vignetting_calibration import VignettingAccumulation, fit_vignetting

    data = _npz_input("acc", random.Random(seed))
    acc = only_own_errors(VignettingAccumulation.load, put(workdir, "acc.npz", data))
    if acc is not None:
        check_vignetting(only_own_errors(fit_vignetting, acc, model="lut"))


# ==================================================================================================
# radical .crf
# ==================================================================================================
def crf_structured(rng: random.Random) -> bytes:
    """A cv::Mat header from the grammar (types, dims, sizes) and a table with hostile values."""
    from radiometry.formats.crf import MAGIC

    cv_type = rng.choice([5, 6, 13, 14, 21, 22, 0, 16, 29, 30, 7, 255])
    rows, cols = rng.choice([(256, 1), (1, 256), (16, 16), (255, 1), (0, 0), (2**31, 2), (65536, 65536), (128, 2)])
    depth, channels = cv_type & 7, (cv_type >> 3) + 1
    table = np.repeat(np.linspace(0, 1, 256)[:, None], channels, axis=1)
    for _ in range(rng.randint(0, 4)):
        table[rng.randrange(256), rng.randrange(channels)] = rng.choice(INTERESTING_FLOATS)
    if rng.random() < 0.2:
        table = table[::-1]
    with np.errstate(over="ignore"):
        body = table.astype({6: "<f8"}.get(depth, "<f4")).tobytes()
    body = body[:rng.choice([len(body), len(body), len(body) - 1, len(body) // 2, 0])]
    return struct.pack("<5I", MAGIC, cv_type, rng.choice([2, 2, 1, 3, 0]), rows, cols) + body


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_radical_crf(workdir, seed):
    from radiometry.formats.crf import read_radical_crf

    rng = random.Random(seed)
    which = rng.random()
    if which < 0.5:
        data = mutate_bytes(seeds()["r.crf"], rng, header=24, floats="<f4")
    elif which < 0.85:
        data = crf_structured(rng)
    else:
        data = random_input(rng)
    check_response(only_own_errors(read_radical_crf, put(workdir, "r.crf", data)))


# ==================================================================================================
# DSO pcalib.txt
# ==================================================================================================
def pcalib_structured(rng: random.Random) -> str:
    """256 increasing values (DSO's layout) with a few hostile tokens, duplicates or drops."""
    values = [f"{v:.6f}" for v in np.sort(np.random.default_rng(rng.randrange(2**32)).uniform(0, 255, 256))]
    for _ in range(rng.randint(0, 3)):
        i = rng.randrange(len(values))
        op = rng.random()
        if op < 0.6:
            values[i] = hostile_token(rng)
        elif op < 0.8:
            del values[i]
        else:
            values.insert(i, values[i])
    return " ".join(values) + rng.choice([" \n", "\n", " vis_exponent: 1.0\n", "\nvis_exponent: 1.0\n"])


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_dso_pcalib(workdir, seed):
    from radiometry.formats.pcalib import read_pcalib

    rng = random.Random(seed)
    which = rng.random()
    if which < 0.5:
        data: bytes | str = mutate_text(seeds()["pcalib.txt"].decode(), rng)
    elif which < 0.85:
        data = pcalib_structured(rng)
    else:
        data = random_input(rng, text=True)
    check_response(only_own_errors(read_pcalib, put(workdir, "pcalib.txt", data)))


# ==================================================================================================
# radical .vgn (LUT and polynomial forms)
# ==================================================================================================
def vgn_header(rng: random.Random) -> bytes:
    """A header line from the grammar with hostile numbers, then the original (or a mutated) matrix."""
    seed = seeds()[rng.choice(["lut.vgn", "poly.vgn"])]
    newline = seed.index(b"\n")
    fields = seed[:newline].decode().split(" ")
    for _ in range(rng.randint(1, 3)):
        i = rng.randint(0, len(fields))
        if i == len(fields):
            fields.append(hostile_token(rng))
        elif i == 0:
            fields[0] = rng.choice([fields[0], "NonparametricVignettingModel", "PolynomialVignettingModel", ""])
        else:
            fields[i] = hostile_token(rng)
    body = seed[newline:]
    if rng.random() < 0.3:
        body = mutate_bytes(body, rng, header=24, floats="<f8")
    return encode(" ".join(fields)) + body


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_radical_vgn(workdir, seed):
    from radiometry.formats.vgn import read_radical_vgn

    rng = random.Random(seed)
    which = rng.random()
    if which < 0.25:
        data = mutate_bytes(seeds()["lut.vgn"], rng, header=64, floats="<f4")
    elif which < 0.5:
        data = mutate_bytes(seeds()["poly.vgn"], rng, header=64, floats="<f8")
    elif which < 0.85:
        data = vgn_header(rng)
    else:
        data = random_input(rng, text=True)
    check_vignetting(only_own_errors(read_radical_vgn, put(workdir, "v.vgn", data)))



@pytest.mark.slow
@fuzz(2000)
@given(seed=SEEDS, suffix=st.sampled_from([".npz", ".crf", ".txt", ".vgn", ".png", ".NPZ", "", ".json"]))
def test_load_dispatchers(workdir, seed, suffix):
    """load_response / load_vignetting (what --response and --vignetting call) on any suffix."""
    from radiometry.formats import load_response, load_vignetting

    rng = random.Random(seed)
    name = rng.choice(["r.npz", "r.crf", "pcalib.txt", "lut.vgn", "poly.npz", "vignette.png"])
    data = mutate_bytes(seeds()[name], rng) if rng.random() < 0.8 else random_input(rng)
    path = put(workdir, "model" + suffix, data)
    check_response(only_own_errors(load_response, path))
    check_vignetting(only_own_errors(load_vignetting, path))
