"""Benchmark: vignetting correction of 640x480 RGB uint8 frames on ONE core.

Compares ``Corrector.correct`` (quantised gain levels, a uint8 table per level, a Numba gather) with a
straightforward NumPy implementation of the same formula ``f(scale * f^-1(I) / V)``
(``radiometry.correction.correct_reference_numpy``) in the same run, and reports frames per second,
their ratio, and the fast path's deviation from the exact float formula.

The process is pinned to one CPU (``os.sched_setaffinity``) and BLAS/Numba are limited to one thread,
so the numbers are single-core numbers. Usage::

    python scripts/bench_correction.py [--width 640 --height 480 --seconds 3]
"""

from __future__ import annotations

import argparse
import sys
import time

from _bench import pin_to_one_core  # before NumPy: one BLAS/OpenMP/Numba thread

import numpy as np  # noqa: E402


def rate(fn, seconds: float, min_runs: int = 5) -> float:
    """Frames per second: the best of three timing windows of about ``seconds / 3`` each."""
    best = 0.0
    for _ in range(3):
        n, start = 0, time.perf_counter()
        while n < min_runs or time.perf_counter() - start < seconds / 3:
            fn()
            n += 1
        best = max(best, n / (time.perf_counter() - start))
    return best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--seconds", type=float, default=3.0, help="timing budget per implementation")
    parser.add_argument("--scale", type=float, default=0.8)
    args = parser.parse_args(argv)
    pinned = pin_to_one_core()
    import numba

    numba.set_num_threads(1)
    from radiometry.correction import Corrector, correct_reference_numpy
    from radiometry.simulation import CameraSpec, SimulatedCamera

    w, h = args.width, args.height
    camera = SimulatedCamera(CameraSpec.preset("xtion", width=w, height=h))  # S-curve CRF, strong vignetting
    response = camera.response
    from radiometry.vignetting import LUTVignetting

    model = LUTVignetting(camera.vignetting)
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(4)]
    corrector = Corrector(response, model)
    corrector.correct(frames[0], scale=args.scale)  # compile / load the kernel, build the tables
    corrector.irradiance(frames[0])
    vmap = model.evaluate(h, w)

    it = iter(range(10**12))
    fast = rate(lambda: corrector.correct(frames[next(it) % 4], scale=args.scale), args.seconds)
    peer = rate(lambda: correct_reference_numpy(frames[next(it) % 4], response, vmap, scale=args.scale),
                args.seconds, min_runs=3)
    irr = rate(lambda: corrector.irradiance(frames[next(it) % 4]), args.seconds)

    out = corrector.correct(frames[0], scale=args.scale).astype(np.int64)
    exact = corrector.correct_exact(frames[0], scale=args.scale).astype(np.float64)
    dev_float = float(np.abs(out - exact).max())
    dev_rounded = int(np.abs(out - np.clip(np.rint(exact), 0, 255)).max())
    frac = float(np.mean(out != np.clip(np.rint(exact), 0, 255)))

    print(f"vignetting correction, {w}x{h} RGB uint8 -> uint8, scale {args.scale}, one core ({pinned})")
    print(f"  Corrector.correct (tables + Numba): {fast:9.1f} frames/s")
    print(f"  NumPy reference, same formula     : {peer:9.1f} frames/s")
    print(f"  ratio                             : {fast / peer:9.1f} x")
    print(f"  Corrector.irradiance (float32)    : {irr:9.1f} frames/s")
    print(f"  deviation from the exact formula  : max {dev_float:.3f} levels (unrounded), max {dev_rounded} level "
          f"after rounding, {100 * frac:.3f}% of values differ")
    print(f"  target >= 1000 frames/s: {'met' if fast >= 1000 else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
