"""Property-based fuzzing of every reader: random and mutated inputs raise only radiomap's own errors.

Each reader is fed (a) valid files, written by the project's own writers, mutated at the byte, line,
token or number level, (b) inputs built from the format's grammar with hostile values (NaN, inf, huge,
negative, non-monotone, wrong shapes and types), and (c) random bytes or text. The property: the reader
returns a valid object (checked) or raises a :class:`~radiometry.errors.RadiomapError` with a one-line
message; any other exception (``ValueError``, ``OverflowError``, ``cv2.error``, ``RecursionError``,
``MemoryError``, ...) is a crash. A reader that runs longer than :data:`EXAMPLE_SECONDS` is a hang
(``signal.setitimer`` raises inside Python code; a ``faulthandler`` watchdog ends the run if C code never
returns).

Hypothesis draws a 64-bit seed per example and the mutators below turn it into an input with
``random.Random(seed)``: a few microseconds per case instead of one Hypothesis draw per edit, so every
reader gets a few thousand cases within seconds. A failure prints the offending input (``note``) and the
seed that reproduces it. Deterministic: ``derandomize=True``, no example database.
``RADIOMAP_FUZZ_SCALE=10`` multiplies every budget for a deeper local run.
"""

from __future__ import annotations

import contextlib
import faulthandler
import functools
import io
import json
import math
import os
import random
import signal
import struct
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

from radiometry.errors import RadiomapError

SCALE = float(os.environ.get("RADIOMAP_FUZZ_SCALE", "1"))
EXAMPLE_SECONDS = 3.0        # one reader call on a few-kilobyte input: normally well under 10 ms
WATCHDOG_SECONDS = 60.0      # C code that never returns: dump the stacks and exit instead of hanging CI
SEEDS = st.integers(0, 2**64 - 1)


def fuzz(n: int):
    """Hypothesis settings of one fuzz strategy: ``n`` examples (times RADIOMAP_FUZZ_SCALE)."""
    return settings(max_examples=max(1, int(n * SCALE)), deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


class Hang(Exception):
    """A reader ran longer than EXAMPLE_SECONDS."""


@contextlib.contextmanager
def time_limit(seconds: float = EXAMPLE_SECONDS):
    def on_alarm(signum, frame):
        raise Hang(f"the reader did not return within {seconds} s")

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    faulthandler.dump_traceback_later(WATCHDOG_SECONDS, exit=True)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        faulthandler.cancel_dump_traceback_later()


def only_own_errors(read, *args, **kwargs):
    """Call ``read``: return its result, or None when it raised a RadiomapError with a one-line message.
    Any other exception propagates and fails the test (Hypothesis then reports the input)."""
    with time_limit():
        try:
            return read(*args, **kwargs)
        except RadiomapError as exc:
            message = str(exc)
            assert message.strip() and "\n" not in message.strip(), f"not a one-line message: {message!r}"
            return None


# ==================================================================================================
# mutators: (valid input, random.Random) -> hostile input
# ==================================================================================================
INTERESTING_U32 = [0, 1, 2, 3, 4, 5, 6, 7, 13, 21, 22, 29, 255, 256, 257, 1023, 65535, 65536, 0x7FFFFFFF,
                   0x80000000, 0xFFFFFFFE, 0xFFFFFFFF, 0xC4A1FDD9]
INTERESTING_FLOATS = [math.nan, math.inf, -math.inf, 0.0, -0.0, -1.0, 1.0, 1e-45, 1e-320, 1e38, 3.5e38, 1e308,
                      -1e308, 0.5, 2.0, 1000.0, 1001.0]
TOKENS = ["nan", "NaN", "-nan", "inf", "-inf", "Infinity", "1e309", "-1e309", "1e-320", "0", "-0", "-1", "1", "2",
          "3", "255", "256", "65535", "1e5", "99999999999999999999999999999", "1" + "0" * 400, "", "abc", "#", "1/0",
          "0/0", "1/3", "1/-2", "\uff11", "\u0661", "1_0", "0x10", "\x00", "\u00e9", "  ", "\t", ",", "1,2", "-",
          "+", ".", "e5", "1e", "3.14.15", "NaN/1", "1e400/1", "0.001", "{", "}", "[", "]", '"', "null", "true",
          "\ufeff1", "1e-7", "0.0000001", "4294967296", "-4294967297"]
HOSTILE_JSON = [None, True, False, 0, -1, 1, 2, 3, 10**30, -(10**30), 10**400, math.nan, math.inf, -math.inf, 1e-320,
                "", "x", "64", [], {}, [1, 2, 3], [[1, 0, 0]] * 3, [None] * 9, [[]] * 9, ["1"] * 9, {"a": 1}]


def hostile_token(rng: random.Random) -> str:
    kind = rng.random()
    if kind < 0.5:
        return rng.choice(TOKENS)
    if kind < 0.7:
        return repr(rng.choice(INTERESTING_FLOATS) * rng.choice([1, -1, 1e10, 1e-10]))
    if kind < 0.85:
        return str(rng.randint(-(10**12), 10**12))
    return f"{rng.uniform(-10, 10):.6f}"


def hostile_json(rng: random.Random, depth: int = 0):
    if depth < 2 and rng.random() < 0.25:
        if rng.random() < 0.5:
            return [hostile_json(rng, depth + 1) for _ in range(rng.randint(0, 4))]
        return {rng.choice(["a", "K", "fx", ""]): hostile_json(rng, depth + 1) for _ in range(rng.randint(0, 3))}
    return rng.choice(HOSTILE_JSON)


def mutate_bytes(seed: bytes, rng: random.Random, *, header: int = 64, floats: str | None = None,
                 max_mutations: int = 6) -> bytes:
    """``seed`` with 1..max_mutations byte edits, half of them within the first ``header`` bytes.
    ``floats`` ('<f4' or '<f8') adds edits that overwrite a value with a hostile float."""
    data = bytearray(seed)
    ops = ["flip", "byte", "insert", "delete", "truncate", "duplicate", "u32"] + (["float"] * 3 if floats else [])
    for _ in range(rng.randint(1, max_mutations)):
        op = rng.choice(ops)
        if data:
            pos = rng.randrange(min(header, len(data))) if rng.random() < 0.5 else rng.randrange(len(data))
        else:
            pos = 0
        if op == "flip" and data:
            data[pos] ^= 1 << rng.randrange(8)
        elif op == "byte" and data:
            data[pos] = rng.choice([0, 1, 0x7F, 0x80, 0xFF, 0x0A, 0x20, 0x2D, rng.randrange(256)])
        elif op == "insert":
            data[pos:pos] = rng.randbytes(rng.randint(1, 16))
        elif op == "delete" and data:
            del data[pos:pos + rng.randint(1, 32)]
        elif op == "truncate":
            del data[pos:]
        elif op == "duplicate" and data:
            data[pos:pos] = data[pos:pos + rng.randint(1, 64)]
        elif op == "u32":
            value = rng.choice(INTERESTING_U32) if rng.random() < 0.7 else rng.randrange(2**32)
            data[pos:pos + 4] = struct.pack(rng.choice(["<I", ">I"]), value)
        elif op == "float" and floats:
            size = np.dtype(floats).itemsize
            pos = rng.randrange(max(len(data) - size, 1))
            with np.errstate(over="ignore"):
                data[pos:pos + size] = np.array([rng.choice(INTERESTING_FLOATS)], dtype=floats).tobytes()
    return bytes(data)


def mutate_text(seed: str, rng: random.Random, *, max_mutations: int = 5) -> str:
    """``seed`` with line and token edits: replace, drop or add tokens (hostile numbers, comments,
    separators), delete, duplicate, swap or insert lines, truncate, CRLF, blank and comment lines."""
    lines = seed.splitlines()
    for _ in range(rng.randint(1, max_mutations)):
        op = rng.choice(["token", "token", "token", "drop_token", "add_token", "del_line", "dup_line", "swap",
                         "new_line", "truncate", "crlf", "blank"])
        i = rng.randrange(len(lines)) if lines else 0
        if op in ("token", "drop_token", "add_token") and lines:
            tokens = lines[i].split(" ")
            j = rng.randrange(len(tokens))
            if op == "token":
                tokens[j] = hostile_token(rng)
            elif op == "drop_token":
                del tokens[j]
            else:
                tokens.insert(j, hostile_token(rng))
            lines[i] = " ".join(tokens)
        elif op == "del_line" and lines:
            del lines[i]
        elif op == "dup_line" and lines:
            lines.insert(i, lines[i])
        elif op == "swap" and len(lines) > 1:
            k = rng.randrange(len(lines))
            lines[i], lines[k] = lines[k], lines[i]
        elif op == "new_line":
            lines.insert(i, " ".join(hostile_token(rng) for _ in range(rng.randint(0, 10))))
        elif op == "truncate" and lines:
            lines[i] = lines[i][:rng.randint(0, len(lines[i]))]
            del lines[i + 1:]
        elif op == "crlf" and lines:
            lines[i] += "\r"
        elif op == "blank":
            lines.insert(i, rng.choice(["", " ", "#", "# comment 1 2 3", "\t", "\x0c"]))
    return "\n".join(lines) + rng.choice(["\n", "", "\n\n"])


def grammar_text(rng: random.Random, columns: list[int], *, max_rows: int = 12) -> str:
    """Rows of hostile numeric tokens whose count is usually one of ``columns`` (so that the reader gets
    past 'wrong number of columns' to the values)."""
    rows = []
    for _ in range(rng.randint(0, max_rows)):
        n = rng.choice(columns) if rng.random() < 0.9 else rng.randint(0, 12)
        rows.append(" ".join(hostile_token(rng) for _ in range(n)))
    return "\n".join(rows) + "\n"


def random_input(rng: random.Random, *, text: bool = False) -> bytes:
    """Random bytes, or random text (ASCII, digits and separators, or any code point), up to 1 KiB."""
    size = rng.randint(0, 1024)
    if not text or rng.random() < 0.3:
        return rng.randbytes(size)
    alphabet = rng.choice(["0123456789.-+eE \n\t#/", "".join(map(chr, range(32, 127))) + "\n",
                           None])
    if alphabet is None:
        chars = [chr(rng.choice([rng.randrange(0x20, 0x7F), rng.randrange(0x80, 0xD800), 0x0A]))
                 for _ in range(size // 2)]
    else:
        chars = [rng.choice(alphabet) for _ in range(size)]
    return "".join(chars).encode("utf-8")


def encode(text: str) -> bytes:
    return text.encode("utf-8", "surrogatepass")


# ==================================================================================================
# valid seed files (written by the project's own writers) and a scratch folder
# ==================================================================================================
W, H = 12, 9


@functools.lru_cache(maxsize=None)
def seeds() -> dict[str, bytes]:
    import tempfile

    from radiometry.formats.crf import write_radical_crf
    from radiometry.formats.dso_vignette import write_dso_vignette
    from radiometry.formats.pcalib import write_pcalib
    from radiometry.formats.vgn import write_radical_vgn
    from radiometry.response import CameraResponse
    from radiometry.vignetting import LUTVignetting, PolynomialVignetting
    from radiometry.vignetting_calibration import VignettingAccumulator

    response = CameraResponse.gamma(2.2)
    yy, xx = np.mgrid[0:H, 0:W]
    r2 = ((xx - (W - 1) / 2) ** 2 + (yy - (H - 1) / 2) ** 2) / (0.25 * (W * W + H * H))
    lut = LUTVignetting(np.repeat((1 - 0.3 * r2)[:, :, None], 3, axis=2).astype(np.float32))
    poly = PolynomialVignetting([[-0.3, 0.05, -0.01]] * 3, [[(W - 1) / 2, (H - 1) / 2]] * 3, (W, H))
    acc = VignettingAccumulator(16, 20, 3, response, block=4)
    for i in range(2):
        acc.add(np.full((16, 20, 3), 150 + i, np.uint8), np.ones((16, 20), bool), index=i)
    out: dict[str, bytes] = {}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        response.save(d / "r.npz")
        CameraResponse.gamma(2.0, channels=1).save(d / "r1.npz")
        lut.save(d / "lut.npz")
        poly.save(d / "poly.npz")
        acc.result(skipped={"saturated": 1}, source="fuzz").save(d / "acc.npz")
        write_radical_crf(d / "r.crf", response)
        write_pcalib(d / "pcalib.txt", response, channel=1)
        write_radical_vgn(lut, d / "lut.vgn")
        write_radical_vgn(poly, d / "poly.vgn")
        write_dso_vignette(lut, d / "vignette.png")
        for p in d.iterdir():
            out[p.name] = p.read_bytes()
    rgb = (np.arange(W * H * 3, dtype=np.uint32).reshape(H, W, 3) % 251).astype(np.uint8)
    out["rgb.png"] = cv2.imencode(".png", rgb)[1].tobytes()
    out["rgb.jpg"] = cv2.imencode(".jpg", rgb)[1].tobytes()
    out["depth.png"] = cv2.imencode(".png", np.full((H, W), 5000, np.uint16))[1].tobytes()
    return out


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


def put(folder: Path, name: str, data: bytes | str) -> Path:
    path = folder / name
    path.write_bytes(encode(data) if isinstance(data, str) else data)
    note(f"{name}: {data[:2000]!r}")
    return path


def _check_response(resp) -> None:
    if resp is not None:
        t = resp.inverse_table
        assert t.shape[0] == 256 and t.shape[1] in (1, 3)
        assert np.all(np.isfinite(t)) and np.all(np.diff(t, axis=0) > 0) and np.allclose(t[-1], 1.0)


def _check_vignetting(model) -> None:
    if model is not None and model.resolution[0] * model.resolution[1] <= 10**6:
        v = model.evaluate()
        assert v.ndim == 3 and v.shape[2] in (1, 3) and v.shape[:2] == model.resolution[::-1]
        assert np.all(np.isfinite(v)) and np.all(v > 0)


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


@fuzz(2000)
@given(seed=SEEDS)
def test_response_npz(workdir, seed):
    from radiometry.response import CameraResponse

    data = _npz_input("response", random.Random(seed))
    _check_response(only_own_errors(CameraResponse.load, put(workdir, "r.npz", data)))


@fuzz(2000)
@given(seed=SEEDS)
def test_vignetting_npz(workdir, seed):
    from radiometry.vignetting import VignettingModel

    data = _npz_input("vignetting", random.Random(seed))
    _check_vignetting(only_own_errors(VignettingModel.load, put(workdir, "v.npz", data)))


@fuzz(600)
@given(seed=SEEDS)
def test_vignetting_accumulation_npz(workdir, seed):
    """Accumulations saved with --save-accumulation: a file that loads can be fitted (or fails cleanly)."""
    from radiometry.vignetting_calibration import VignettingAccumulation, fit_vignetting

    data = _npz_input("acc", random.Random(seed))
    acc = only_own_errors(VignettingAccumulation.load, put(workdir, "acc.npz", data))
    if acc is not None:
        _check_vignetting(only_own_errors(fit_vignetting, acc, model="lut"))


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


@fuzz(2000)
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
    _check_response(only_own_errors(read_radical_crf, put(workdir, "r.crf", data)))


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


@fuzz(2000)
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
    _check_response(only_own_errors(read_pcalib, put(workdir, "pcalib.txt", data)))


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


@fuzz(2000)
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
    _check_vignetting(only_own_errors(read_radical_vgn, put(workdir, "v.vgn", data)))


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


@fuzz(1500)
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
    _check_vignetting(only_own_errors(read_dso_vignette, put(workdir, "vignette.png", data)))


@fuzz(1500)
@given(seed=SEEDS)
def test_colour_and_depth_images(workdir, seed):
    from radiometry.fileio import read_depth, read_rgb

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


@fuzz(600)
@given(seed=SEEDS, suffix=st.sampled_from([".npz", ".crf", ".txt", ".vgn", ".png", ".NPZ", "", ".json"]))
def test_load_dispatchers(workdir, seed, suffix):
    """load_response / load_vignetting (what --response and --vignetting call) on any suffix."""
    from radiometry.formats import load_response, load_vignetting

    rng = random.Random(seed)
    name = rng.choice(["r.npz", "r.crf", "pcalib.txt", "lut.vgn", "poly.npz", "vignette.png"])
    data = mutate_bytes(seeds()[name], rng) if rng.random() < 0.8 else random_input(rng)
    path = put(workdir, "model" + suffix, data)
    _check_response(only_own_errors(load_response, path))
    _check_vignetting(only_own_errors(load_vignetting, path))


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


@fuzz(1500)
@given(seed=SEEDS)
def test_times_file(workdir, seed):
    from radiometry.response_fit import read_times_file

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


@fuzz(500)
@given(seed=SEEDS)
def test_bracket_folder_with_mutated_times(bracket_folder, seed):
    """load_brackets (what 'radiomap response' reads): the times file against the folder's images."""
    from radiometry.response_fit import load_brackets

    put(bracket_folder, "times.txt", times_input(random.Random(seed)))
    result = only_own_errors(load_brackets, bracket_folder)
    if result is not None:
        images, times, names = result
        assert len(images) == len(times) == len(names) == 3 and np.all(times > 0)


# ==================================================================================================
# TUM lists and trajectories, 7-Scenes poses, Redwood .log, camera intrinsics, simulator manifests
# ==================================================================================================
TUM_LIST = "# color images\n# timestamp filename\n1305031102.175304 rgb/1305031102.175304.png\n" \
           "1305031102.211214 rgb/1305031102.211214.png\n1305031102.243211 rgb/1305031102.243211.png\n"
TUM_TRAJ = "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n" \
           "1305031102.1758 1.3405 0.6266 1.6575 0.6574 0.6126 -0.2949 -0.3248\n" \
           "1305031102.2058 1.3303 0.6256 1.6464 0.6579 0.6161 -0.2932 -0.3189\n" \
           "1305031102.2358 1.3160 0.6254 1.6302 0.6583 0.6200 -0.2907 -0.3136\n"
POSE = "0.99 0.01 -0.1 0.1\n-0.01 0.99 0.0 -0.2\n0.1 0.0 0.99 1.5\n0 0 0 1\n"
LOG = "0 0 3\n1 0 0 0.5\n0 1 0 0\n0 0 1 1\n0 0 0 1\n1 1 3\n1 0 0 0.6\n0 1 0 0\n0 0 1 1\n0 0 0 1\n"
INTRINSICS_TXT = "525.0 0 319.5\n0 525.0 239.5\n0 0 1\n"
CAMERA_JSON = json.dumps({"width": 640, "height": 480,
                          "intrinsic_matrix": [525.0, 0, 0, 0, 525.0, 0, 319.5, 239.5, 1]})


def text_input(rng: random.Random, seed_text: str, columns: list[int], max_rows: int = 12) -> bytes | str:
    which = rng.random()
    if which < 0.6:
        return mutate_text(seed_text, rng)
    if which < 0.85:
        return grammar_text(rng, columns, max_rows=max_rows)
    return random_input(rng, text=True)


@fuzz(1500)
@given(seed=SEEDS)
def test_tum_list(workdir, seed):
    from mapping.datasets._common import read_stamped_list

    data = text_input(random.Random(seed), TUM_LIST, [2])
    rows = only_own_errors(read_stamped_list, put(workdir, "rgb.txt", data))
    if rows is not None:
        assert all(math.isfinite(t) and name for t, name, _ in rows)


@fuzz(1500)
@given(seed=SEEDS)
def test_tum_trajectory(workdir, seed):
    from mapping.metrics import read_tum_trajectory

    data = text_input(random.Random(seed), TUM_TRAJ, [8])
    result = only_own_errors(read_tum_trajectory, put(workdir, "groundtruth.txt", data))
    if result is not None:
        stamps, poses = result
        assert len(stamps) == len(poses) and np.all(np.isfinite(poses)) and np.all(np.isfinite(stamps))


@pytest.fixture(scope="module")
def tum_folder(workdir) -> Path:
    root = workdir / "rgbd_dataset_freiburg1_fuzz"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for stamp in ("1305031102.175304", "1305031102.211214", "1305031102.243211"):
        cv2.imwrite(str(root / "rgb" / f"{stamp}.png"), np.full((48, 64, 3), 128, np.uint8))
        cv2.imwrite(str(root / "depth" / f"{stamp}.png"), np.full((48, 64), 10000, np.uint16))
    return root


TUM_FILES = {"rgb.txt": TUM_LIST, "depth.txt": TUM_LIST.replace("rgb/", "depth/"), "groundtruth.txt": TUM_TRAJ,
             "intrinsics.txt": "60.0 60.0 31.5 23.5\n"}


@fuzz(800)
@given(seed=SEEDS, which=st.sampled_from(sorted(TUM_FILES)))
def test_tum_folder_with_one_mutated_file(tum_folder, seed, which):
    """A whole TUM folder (three real frames) with one text file mutated: open it, read every frame and
    the ground truth, as 'radiomap reconstruct' does."""
    from mapping.datasets.tum import TUMDataset

    rng = random.Random(seed)
    for name, text in TUM_FILES.items():
        columns = {"groundtruth.txt": [8], "intrinsics.txt": [3, 4]}.get(name, [2])
        put(tum_folder, name, text_input(rng, text, columns, max_rows=5) if name == which else text)

    def open_and_read():
        ds = TUMDataset(tum_folder)
        frames = [ds[i] for i in range(len(ds))]
        gt = ds.ground_truth()
        assert gt is None or np.all(np.isfinite(gt[1]))
        return frames

    only_own_errors(open_and_read)


@fuzz(1000)
@given(seed=SEEDS)
def test_sevenscenes_pose(workdir, seed):
    from mapping.datasets._common import read_pose_matrix_file

    data = text_input(random.Random(seed), POSE, [4], max_rows=5)
    pose = only_own_errors(read_pose_matrix_file, put(workdir, "frame-000000.pose.txt", data))
    if pose is not None:
        assert pose.shape == (4, 4) and np.all(np.isfinite(pose))


@fuzz(1500)
@given(seed=SEEDS)
def test_redwood_log(workdir, seed):
    from mapping.datasets.redwood import read_log_trajectory

    data = text_input(random.Random(seed), LOG, [3, 4, 4, 4, 4], max_rows=15)
    poses = only_own_errors(read_log_trajectory, put(workdir, "trajectory.log", data))
    if poses is not None:
        assert all(p.shape == (4, 4) and np.all(np.isfinite(p)) for p in poses.values())


def camera_json(rng: random.Random) -> str:
    """An Open3D camera JSON (or the K / fx,fy,cx,cy forms) with hostile values, lengths and types."""
    doc = json.loads(CAMERA_JSON)
    key = rng.choice(["intrinsic_matrix", "K", "fx"])
    if key != "intrinsic_matrix":
        doc.pop("intrinsic_matrix")
    if key == "fx":
        doc.update(fx=525.0, fy=525.0, cx=319.5, cy=239.5)
        doc[rng.choice(["fx", "fy", "cx", "cy"])] = hostile_json(rng)
    else:
        flat = [525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1] if key == "K" else list(doc["intrinsic_matrix"])
        op = rng.choice(["element", "length", "whole"])
        if op == "element":
            flat[rng.randrange(9)] = hostile_json(rng)
            doc[key] = flat
        elif op == "length":
            doc[key] = flat[:rng.randint(0, 8)] + flat[:rng.randint(0, 3)]
        else:
            doc[key] = hostile_json(rng)
    if rng.random() < 0.05:
        return "[" * 100_000
    return json.dumps(doc, allow_nan=True)


@fuzz(1000)
@given(seed=SEEDS)
def test_camera_intrinsics_json(workdir, seed):
    from mapping.datasets._common import read_intrinsics_file

    rng = random.Random(seed)
    data = camera_json(rng) if rng.random() < 0.6 else text_input(rng, CAMERA_JSON, [1])
    K = only_own_errors(read_intrinsics_file, put(workdir, "camera_primesense.json", data))
    if K is not None:
        assert K.shape == (3, 3) and np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0


@fuzz(1000)
@given(seed=SEEDS)
def test_camera_intrinsics_txt(workdir, seed):
    from mapping.datasets._common import read_intrinsics_file

    rng = random.Random(seed)
    data = text_input(rng, rng.choice([INTRINSICS_TXT, "525 525 319.5 239.5\n"]), [3, 4], max_rows=4)
    K = only_own_errors(read_intrinsics_file, put(workdir, "camera-intrinsics.txt", data))
    if K is not None:
        assert K.shape == (3, 3) and np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0


MANIFEST = json.dumps({"format": "radiomap-sim", "version": 1, "kind": "room", "width": 64, "height": 48,
                       "K": [[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]], "depth_scale": 5000.0, "n_frames": 3})


@fuzz(500)
@given(seed=SEEDS)
def test_simulated_manifest(tum_folder, seed):
    """A simulator manifest beside a valid TUM folder: SimulatedDataset opens it or fails cleanly."""
    from mapping.datasets.simulated import MANIFEST as NAME, SimulatedDataset

    rng = random.Random(seed)
    doc = json.loads(MANIFEST)
    for _ in range(rng.randint(1, 3)):
        doc[rng.choice(sorted(doc))] = hostile_json(rng)
    data = json.dumps(doc, allow_nan=True) if rng.random() < 0.7 else mutate_text(MANIFEST, rng)
    for name, text in TUM_FILES.items():
        put(tum_folder, name, text)
    put(tum_folder, NAME, data)
    try:
        only_own_errors(lambda: SimulatedDataset(tum_folder)[0])
    finally:
        (tum_folder / NAME).unlink()
