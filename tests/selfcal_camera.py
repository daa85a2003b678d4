"""An RGB-D camera for self-calibration studies, written independently of radiomap's simulator (issue 29).

Nothing here imports ``radiometry``; from ``mapping`` only the frame container (:class:`RGBDFrame`,
:class:`ArrayDataset`). The scene is the inside of a box with smooth, view-independent radiance (Lambertian walls
whose albedo varies slowly, with a few flat patches); depth is the exact ray-box distance. The camera:

- vignetting from a real camera: the EuRoC MT9V034's measured ``vignette.png`` (``../shared/data``), resampled to
  the image, its optical centre moved off the principal point (where the moved image reaches past the measured
  one, the lens's radial fall-off continues from the border), raised to a per-channel power (chromatic
  vignetting; corners 0.45-0.68 at 640x480, 0.39-0.73 at 320x240; an Asus Xtion's are about 0.5), times a sensor-shading gradient and a dust shadow (the
  non-radial structure real vignettes carry); without the shared data an even polynomial of the same strength;
- auto exposure: a lagging controller that drives the mean level of the view to a target; auto white balance: a
  lagging grey-world gain per channel (both act as a per-channel ``k`` per frame before the sensor);
- the sensor and response of :mod:`camera_pipelines` (shot and read noise on irradiance, full-well clip, a real
  measured response: EuRoC's ``pcalib.txt``, or gamma 2.2 without the shared data, 8 bits).

Trajectories (:data:`MOTIONS`): ``scan`` (hand-held back and forth: yaw and pitch oscillations, sideways steps, a
little roll) and ``pan`` (one steady turn, as many real recordings are).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from camera_pipelines import expose
from response_curves import SHARED_DATA, euroc_curve, gamma_curve

EUROC_VIGNETTE = SHARED_DATA / "vignetting" / "euroc_mt9v034_752x480" / "vignette.png"
MOTIONS = ("scan", "pan")
#: per-channel power on the real vignette (chromatic vignetting: red falls off most)
POWERS = (3.0, 2.6, 2.2)


@dataclass
class Truth:
    """What the camera did: ``vignetting`` (H, W, 3) with V = 1 at its brightest, ``exposures`` (F, 3) per-channel
    ``k`` (exposure x white balance), ``table`` the inverse response (256,), ``optical_centre`` (x, y)."""

    vignetting: np.ndarray
    exposures: np.ndarray
    table: np.ndarray
    optical_centre: tuple[float, float]


def _look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Camera-to-world pose (OpenCV camera: x right, y down, z forward), world up +y."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose


def _sample_extended(real: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """``real`` (the measured vignette) at the points ``(mx, my)``, bilinear. The re-centred image reaches past the
    measured one (its top ~20 and bottom ~35 rows at 640x480): there the nearest measured value is continued by the
    lens's radial fall-off (an even polynomial in the radius, fitted to ``log real``) from that border point out to
    the point, rather than repeating the border row (a flat band no lens makes)."""
    import cv2

    rh, rw = real.shape
    half_diag2 = (rw / 2) ** 2 + (rh / 2) ** 2

    def r2(x, y):
        return ((x - (rw - 1) / 2) ** 2 + (y - (rh - 1) / 2) ** 2) / half_diag2

    gy, gx = np.mgrid[0:rh:4, 0:rw:4]
    q = r2(gx, gy).ravel()
    coef = np.linalg.lstsq(np.stack([np.ones_like(q), q, q ** 2, q ** 3], axis=1),
                           np.log(np.maximum(real[gy, gx].ravel(), 1e-3)), rcond=None)[0]

    def falloff(x, y):
        q = r2(x, y)
        return coef[1] * q + coef[2] * q ** 2 + coef[3] * q ** 3

    bx, by = np.clip(mx, 0, rw - 1), np.clip(my, 0, rh - 1)
    inside = cv2.remap(real.astype(np.float32), bx.astype(np.float32), by.astype(np.float32), cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    return inside * np.exp(falloff(mx, my) - falloff(bx, by))


def true_vignetting(width: int, height: int, *, offset=(12.0, -7.0)) -> tuple[np.ndarray, tuple[float, float]]:
    """V (H, W, 3), 1 at its brightest, and its optical centre (module doc)."""
    import cv2

    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    cx, cy = (width - 1) / 2 + offset[0], (height - 1) / 2 + offset[1]
    radius = np.hypot(width / 2, height / 2)
    if EUROC_VIGNETTE.is_file():
        real = cv2.imread(str(EUROC_VIGNETTE), cv2.IMREAD_UNCHANGED).astype(np.float64)
        real /= real.max()
        # the real vignette as a function of the normalised radius from its own centre, re-centred on (cx, cy)
        rh, rw = real.shape
        scale = np.hypot(rw / 2, rh / 2) / radius
        mx = (xs - cx) * scale + (rw - 1) / 2
        my = (ys - cy) * scale + (rh - 1) / 2
        base = np.clip(_sample_extended(real, mx, my), 0.05, 1.0)
    else:
        r2 = ((xs - cx) ** 2 + (ys - cy) ** 2) / radius ** 2
        base = np.clip(1 - 0.2 * r2 - 0.02 * r2 ** 2, 0.05, 1.0)
    shading = 1.0 + 0.025 * (xs - cx) / width - 0.015 * (ys - cy) / height            # sensor shading
    dust = 1.0 - 0.04 * np.exp(-((xs - 0.3 * width) ** 2 + (ys - 0.62 * height) ** 2) / (2 * (0.03 * width) ** 2))
    v = np.stack([base ** p * shading * dust for p in POWERS], axis=2)
    return v / v.max(axis=(0, 1), keepdims=True), (cx, cy)


class _Room:
    """The inside of the box ``[-1.6, 1.6] x [-1.25, 1.25] x [-1.0, 3.4]`` with smooth albedo and flat patches."""

    lo = np.array([-1.6, -1.25, -1.0])
    hi = np.array([1.6, 1.25, 3.4])

    def __init__(self, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.freq = rng.uniform(1.0, 3.0, size=(3, 3))
        self.phase = rng.uniform(0, 2 * np.pi, size=(3, 3))
        self.base = rng.uniform(0.35, 0.55, size=3)
        self.patches = [(rng.uniform(self.lo, self.hi), rng.uniform(0.25, 0.5), rng.uniform(0.6, 1.5, 3))
                        for _ in range(14)]

    def cast(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(dirs > 0, (self.hi - origin) / dirs, np.where(dirs < 0, (self.lo - origin) / dirs, np.inf))
        return t.min(axis=1)

    def radiance(self, p: np.ndarray) -> np.ndarray:
        out = np.empty((len(p), 3))
        for c in range(3):
            out[:, c] = self.base[c] * (1 + 0.35 * np.sin(p @ self.freq[c] + self.phase[c].sum()))
        for centre, size, colour in self.patches:         # flat square patches (posters, boxes)
            inside = np.all(np.abs(p - centre) < size, axis=1)
            out[inside] *= colour
        return np.clip(out, 0.03, 2.0)


def _trajectory(motion: str, n: int) -> list[np.ndarray]:
    s = np.linspace(0.0, 1.0, n)
    poses = []
    for u in s:
        if motion == "pan":       # one steady turn on the spot (a tripod-like pan), slight hand shake
            yaw, pitch, roll = np.radians(-38 + 76 * u), np.radians(2.0), 0.0
            eye = np.array([0.0, 0.0, 0.2]) + 0.004 * np.array([np.sin(37 * u), np.cos(23 * u), 0.0])
        elif motion == "scan":    # hand-held back and forth: yaw and pitch oscillate, sideways steps, some roll
            yaw = np.radians(28 * np.sin(2 * np.pi * 1.5 * u))
            pitch = np.radians(12 * np.sin(2 * np.pi * 2.3 * u + 0.7))
            roll = np.radians(6 * np.sin(2 * np.pi * 1.1 * u))
            eye = np.array([0.35 * np.sin(2 * np.pi * 0.8 * u), 0.12 * np.sin(2 * np.pi * 1.7 * u), 0.1 + 0.3 * u])
        else:
            raise ValueError(f"motion must be one of {MOTIONS}, got {motion!r}")
        target = eye + np.array([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
        poses.append(_look_at(eye, target, roll))
    return poses


def selfcal_sequence(motion: str = "scan", *, frames: int = 80, width: int = 640, height: int = 480,
                     seed: int = 0, auto_exposure: bool = True, auto_white_balance: bool = True,
                     target_level: float = 0.30):
    """``(dataset, truth)``: an :class:`mapping.datasets.in_memory.ArrayDataset` of the camera above and a
    :class:`Truth`. target_level: the auto exposure's target mean linear value of the view."""
    from mapping.datasets.base import RGBDFrame
    from mapping.datasets.in_memory import ArrayDataset

    room = _Room(seed)
    rng = np.random.default_rng(seed + 1)
    table = euroc_curve()
    table = gamma_curve(2.2) if table is None else table
    v_true, centre = true_vignetting(width, height)
    f = 0.82 * width
    K = np.array([[f, 0, (width - 1) / 2 + 3.0], [0, f, (height - 1) / 2 - 2.0], [0, 0, 1.0]])
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(xx - K[0, 2]) / f, (yy - K[1, 2]) / f, np.ones_like(xx)], axis=-1).reshape(-1, 3)
    k = np.full(3, 0.9)
    out, ks = [], []
    for i, pose in enumerate(_trajectory(motion, frames)):
        dirs = rays @ pose[:3, :3].T
        t = room.cast(pose[:3, 3], dirs)
        radiance = room.radiance(pose[:3, 3] + t[:, None] * dirs).reshape(height, width, 3)
        seen = radiance * v_true
        if i > 0 and (auto_exposure or auto_white_balance):   # lagging controllers on what the last frame showed
            mean = seen.reshape(-1, 3).mean(axis=0) * k
            if auto_exposure:
                k = k * (target_level / mean.mean()) ** 0.35
            if auto_white_balance:
                grey = mean / mean.mean()
                k = k * grey[1] / grey ** 0.3
        ks.append(k.copy())
        rgb = expose(seen * k, 1.0, table, rng=rng)
        depth = (t.reshape(height, width)).astype(np.float32)
        out.append(RGBDFrame(index=i, timestamp=i / 30.0, rgb=rgb, depth=depth, K=K, pose=pose, name=f"f{i:03d}"))
    ks = np.array(ks)
    return ArrayDataset(out, name=f"selfcal-{motion}"), Truth(v_true, ks / ks[0], table, centre)
