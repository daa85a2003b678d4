"""Benchmark: the look-up designs tried for the uint8 correction on CPUs without AVX-512 VBMI (issue 33, item 4).

``Corrector.correct`` runs the scalar gather ``out = table[q + k[c, I]]`` where the CPU lacks AVX-512 VBMI and
GFNI. The issue suggested a smaller table and vectorised gathers to lift it to 25 % of the in-cache memory floor.
This script compiles C prototypes of those (with the system's C compiler, into a temporary folder) and times them on
the xtion preset's real plan (640x480 RGB, random levels, scale 0.8) in one process pinned to one core, against the
extension's own scalar gather:

- ``scalar``: the extension's ``lookup_rgb`` (the path CPUs without VBMI run);
- ``no-check``: the same loop without its per-value bounds check (the caller checks ``max q + max k`` once);
- ``small-table``: ``no-check`` with every index folded into 4 kB, i.e. a table in L1 (wrong output: it measures
  what a smaller table could gain at best);
- ``avx2-gather``: two AVX2 ``vpgatherdd`` per 8 values (``k``, then the table), bit-identical output.

Rates are the best of ``--repeats`` rounds of ``--calls`` calls each, by CPU time. Usage::

    python scripts/bench_correction_alternatives.py [--calls 300 --repeats 3]
"""

from __future__ import annotations

import argparse
import ctypes
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bench import pin_to_one_core  # before NumPy: one BLAS/OpenMP/Numba thread

import numpy as np  # noqa: E402

SOURCE = r"""
#include <immintrin.h>
#include <stddef.h>
#include <stdint.h>

void no_check(const uint8_t *restrict img, const uint16_t *restrict q, const uint32_t *restrict k,
              const uint8_t *restrict table, uint32_t fold, uint8_t *restrict out, ptrdiff_t pixels)
{
    for (ptrdiff_t p = 0; p < pixels; p++) {
        ptrdiff_t b = 3 * p;
        out[b] = table[((uint32_t)q[b] + k[img[b]]) & fold];
        out[b + 1] = table[((uint32_t)q[b + 1] + k[256 + img[b + 1]]) & fold];
        out[b + 2] = table[((uint32_t)q[b + 2] + k[512 + img[b + 2]]) & fold];
    }
}

__attribute__((target("avx2")))
void avx2_gather(const uint8_t *img, const uint16_t *q, const uint32_t *k, const uint8_t *table, uint8_t *out,
                 ptrdiff_t n)
{
    int32_t o[24];
    for (int i = 0; i < 24; i++)
        o[i] = 256 * (i % 3);
    __m256i off[3];
    for (int j = 0; j < 3; j++)
        off[j] = _mm256_loadu_si256((const __m256i *)(o + 8 * j));
    ptrdiff_t i = 0;
    for (; i + 24 <= n; i += 24)
        for (int j = 0; j < 3; j++) {
            __m256i v = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)(img + i + 8 * j)));
            __m256i kk = _mm256_i32gather_epi32((const int *)k, _mm256_add_epi32(v, off[j]), 4);
            __m256i qq = _mm256_cvtepu16_epi32(_mm_loadu_si128((const __m128i *)(q + i + 8 * j)));
            __m256i t = _mm256_i32gather_epi32((const int *)table, _mm256_add_epi32(kk, qq), 1);
            t = _mm256_and_si256(t, _mm256_set1_epi32(255));
            __m128i p = _mm_packus_epi32(_mm256_castsi256_si128(t), _mm256_extracti128_si256(t, 1));
            _mm_storel_epi64((__m128i *)(out + i + 8 * j), _mm_packus_epi16(p, p));
        }
    for (; i < n; i++)
        out[i] = table[q[i] + k[256 * (i % 3) + img[i]]];
}
"""


def has_avx2() -> bool:
    """Whether this CPU has AVX2 (Linux's /proc/cpuinfo; False elsewhere: the prototype is then not run)."""
    try:
        return " avx2" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


def build(folder: Path) -> ctypes.CDLL:
    """Compile :data:`SOURCE` into ``folder``; SystemExit with the reason when there is no C compiler."""
    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        raise SystemExit("bench_correction_alternatives: no C compiler (cc, gcc or clang) on PATH; install one")
    src, lib = folder / "alternatives.c", folder / "alternatives.so"
    src.write_text(SOURCE)
    done = subprocess.run([cc, "-O3", "-shared", "-fPIC", str(src), "-o", str(lib)], capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"bench_correction_alternatives: {cc} failed: {done.stderr.strip().splitlines()[-1]}")
    return ctypes.CDLL(str(lib))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=300, help="calls per timing round (default 300)")
    parser.add_argument("--repeats", type=int, default=3, help="timing rounds, best taken (default 3)")
    args = parser.parse_args(argv)
    pinned = pin_to_one_core()
    from radiometry.correction import Corrector, _kernels
    from radiometry.simulation import CameraSpec, SimulatedCamera
    from radiometry.vignetting import LUTVignetting

    h, w = 480, 640
    camera = SimulatedCamera(CameraSpec.preset("xtion", width=w, height=h))
    scalar = Corrector(camera.response, LUTVignetting(camera.vignetting), simd=False)
    frame = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    scalar.correct(frame, scale=0.8)
    q, k, table = scalar._fast_tables(h, w, 3, 0.8)[:3]   # the plan the scalar gather reads
    q = np.ascontiguousarray(q.reshape(-1))
    img = frame.reshape(-1)
    lookup_rgb = _kernels()[0]
    reference = np.empty_like(img)
    lookup_rgb(img, q, k, table, reference)
    padded = np.concatenate([table, np.zeros(4, np.uint8)])   # a 32-bit gather at the last byte reads 3 past it
    outs = {name: np.empty_like(img) for name in ("no-check", "small-table", "avx2-gather")}
    P = ctypes.c_void_p
    with tempfile.TemporaryDirectory() as tmp:
        lib = build(Path(tmp))
        fold_all = ctypes.c_uint32(0xFFFFFFFF)
        runs = {
            "scalar": lambda: lookup_rgb(img, q, k, table, reference),
            "no-check": lambda: lib.no_check(P(img.ctypes.data), P(q.ctypes.data), P(k.ctypes.data),
                                             P(table.ctypes.data), fold_all, P(outs["no-check"].ctypes.data),
                                             ctypes.c_ssize_t(h * w)),
            "small-table": lambda: lib.no_check(P(img.ctypes.data), P(q.ctypes.data), P(k.ctypes.data),
                                                P(table.ctypes.data), ctypes.c_uint32(4095),
                                                P(outs["small-table"].ctypes.data), ctypes.c_ssize_t(h * w)),
        }
        if has_avx2():
            runs["avx2-gather"] = lambda: lib.avx2_gather(P(img.ctypes.data), P(q.ctypes.data), P(k.ctypes.data),
                                                         P(padded.ctypes.data), P(outs["avx2-gather"].ctypes.data),
                                                         ctypes.c_ssize_t(img.size))
        else:
            print("no AVX2 on this CPU (or not Linux): the gather prototype is left out")
        for fn in runs.values():
            fn()
        best = dict.fromkeys(runs, 0.0)
        for _ in range(args.repeats):
            for name, fn in runs.items():
                start = time.process_time()
                for _ in range(args.calls):
                    fn()
                best[name] = max(best[name], args.calls / max(time.process_time() - start, 1e-9))
    print(f"uint8 correction look-ups, 640x480 RGB, xtion preset, table {table.nbytes:,} bytes, gain indices "
          f"{int(q.min())}..{int(q.max())}; one core ({pinned}); frames/s, best of {args.repeats} x {args.calls} "
          f"calls (CPU time)")
    for name, value in best.items():
        same = "" if name == "scalar" else ("  same output" if np.array_equal(outs[name], reference) else
                                            "  (output differs: a speed bound only)")
        print(f"  {name:12s} {value:9.0f}  ({value / best['scalar']:.2f}x the scalar gather){same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
