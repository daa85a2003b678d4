"""Shared machinery of the reader fuzz tests (``tests/test_fuzz_readers_*.py``): random and mutated inputs
must raise only radiomap's own errors.

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

Per-case cost: the test files import the module-scoped fixtures :func:`workdir` (a scratch folder on
``/dev/shm`` when there is one: rewriting a file on the ext4 checkout costs ~0.4 ms, on tmpfs ~0.01 ms) and
:func:`fuzz_watchdog` (autouse: the ``faulthandler`` watchdog is armed once and re-armed every
``WATCHDOG_SECONDS / 2`` instead of around every call: arming and cancelling it starts and joins a thread,
2 ms per case on a loaded machine). Both were most of the cost of a case.
"""

from __future__ import annotations

import contextlib
import faulthandler
import functools
import math
import os
import random
import signal
import struct
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, note, settings
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


_watchdog_armed_at: list[float | None] = [None]


def _arm_watchdog() -> None:
    """Keep the faulthandler watchdog armed: a call that starts now is ended within WATCHDOG_SECONDS."""
    now = time.monotonic()
    armed = _watchdog_armed_at[0]
    if armed is None or now - armed > WATCHDOG_SECONDS / 2:
        faulthandler.dump_traceback_later(WATCHDOG_SECONDS, exit=True)
        _watchdog_armed_at[0] = now


@pytest.fixture(scope="module", autouse=True)
def fuzz_watchdog():
    """Disarm the watchdog after a fuzz module (import this fixture into every fuzz test file)."""
    yield
    faulthandler.cancel_dump_traceback_later()
    _watchdog_armed_at[0] = None


@contextlib.contextmanager
def time_limit(seconds: float = EXAMPLE_SECONDS):
    def on_alarm(signum, frame):
        raise Hang(f"the reader did not return within {seconds} s")

    _arm_watchdog()
    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


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
    """A scratch folder for the fuzzed files: on tmpfs (/dev/shm) when available, else pytest's tmp."""
    shm = Path("/dev/shm")
    if shm.is_dir() and os.access(shm, os.W_OK):
        with tempfile.TemporaryDirectory(prefix="radiomap-fuzz-", dir=shm) as tmp:
            yield Path(tmp)
    else:
        yield tmp_path_factory.mktemp("fuzz")


def put(folder: Path, name: str, data: bytes | str) -> Path:
    path = folder / name
    path.write_bytes(encode(data) if isinstance(data, str) else data)
    note(f"{name}: {data[:2000]!r}")
    return path


def check_response(resp) -> None:
    if resp is not None:
        t = resp.inverse_table
        assert t.shape[0] == 256 and t.shape[1] in (1, 3)
        assert np.all(np.isfinite(t)) and np.all(np.diff(t, axis=0) > 0) and np.allclose(t[-1], 1.0)


def check_vignetting(model) -> None:
    if model is not None and model.resolution[0] * model.resolution[1] <= 10**6:
        v = model.evaluate()
        assert v.ndim == 3 and v.shape[2] in (1, 3) and v.shape[:2] == model.resolution[::-1]
        assert np.all(np.isfinite(v)) and np.all(v > 0)
