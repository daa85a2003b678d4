"""Varied depth images and intrinsics for comparing radiomap's vertex and normal maps with Open3D's
(tests/test_surface_maps.py, scripts/stress_surface_maps.py). Written without radiomap: NumPy only."""

from __future__ import annotations

import numpy as np

SIZES = ((480, 640), (240, 320), (120, 160), (61, 83), (64, 48), (65, 7), (17, 9), (1, 5), (7, 1), (2, 2))


def depth_case(rng: np.random.Generator, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A depth image (float32 metres, NaN holes, some zeros, steps, noise; sometimes tiny so that normals fall below
    Open3D's 1e-5 floor, sometimes a flat plane) and an intrinsic matrix (principal point possibly outside)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    d = 1.5 + 0.5 * np.sin(xx / rng.uniform(2, 50)) + 0.3 * np.cos(yy / rng.uniform(2, 50))
    d += (xx > rng.integers(w + 1)) * rng.uniform(0, 2)          # a depth step
    d += rng.normal(0, rng.uniform(0, 0.01), d.shape)             # sensor noise
    kind = rng.integers(5)
    if kind == 0:
        d *= 1e-3                                                 # millimetre scene: normals below the floor
    elif kind == 1:
        d = np.full_like(d, rng.uniform(0.3, 4))                  # a fronto-parallel plane
    d = d.astype(np.float32)
    d[rng.random(d.shape) < rng.uniform(0, 0.4)] = np.nan          # holes
    if rng.random() < 0.3:
        d[rng.random(d.shape) < 0.1] = 0.0                        # zeros (not NaN) left in
    K = np.array([[rng.uniform(50, 900), 0, rng.uniform(-10, w + 10)],
                  [0, rng.uniform(50, 900), rng.uniform(-10, h + 10)], [0, 0, 1]])
    return d, K


def same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal bit for bit, NaN where NaN (its payload aside)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    nan = np.isnan(a)
    return bool(np.array_equal(nan, np.isnan(b)) and np.array_equal(a[~nan].view(np.uint32), b[~nan].view(np.uint32)))
