"""What a self-calibration cannot know, and what looks wrong in it: the tilt ambiguity and V's plausibility.

**The tilt ambiguity.** A sighting images at ``log E = kappa_frame + log V(x) + l_point``. Add a tilt
``a (x - cx) / R`` to ``log V``: when every point moves across the image by one shift ``d_frame`` per frame (a
camera that pans), ``a x`` splits into ``a x_point + a d_frame`` and is absorbed exactly by the radiances and the
exposures; the fit cannot tell a tilted V from an exposure drift. Parallax, rotation about the optical axis and
turning back and forth break the tie, more or less. :func:`tilt_visibility` measures how much: the weighted
sightings' tilt field with the best radiances and exposures removed (what the data can see of a tilt), as a share
of the same field with only the radiances removed (what they would see with the exposures known). Near 0 the
tilt is open: a percent of tilt costs the fit less than the systematic errors every real sequence has, so the
solver cannot choose it from the data and holds it near the physically plausible member (V centred near the
principal point, no added tilt), and the stated standard error must carry what is not known
(:func:`tilt_stderr`).

**Plausibility** (:func:`plausibility`): a V brighter away from its centre than at it, or with dark blobs inside
the image, is not a lens's vignetting; the usual causes are named (:data:`CAUSES`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: below this share of a tilt's variance left once exposures and radiances are fitted, the tilt is called open
#: (measured on the independent camera of tests/selfcal_camera.py, 320x240 and 640x480: a steady pan leaves
#: 0.08 % left-right, and its tilt then came out 3-4 levels wrong; a hand-held scan 0.49-0.88 %; real recordings
#: 0.07-0.09 % (the kitchen's first 50 frames, the RealSense office) to 0.45 % (the kitchen's 100))
OPEN_VISIBILITY = 0.0012
#: at or above this share the data pin the tilt well enough to leave the grid's tilt free; in between, the tilt comes
#: from the polynomial's free centre only (measured: the 15-frame quick demo, 0.16 % / 0.36 %, 1.57 levels with it
#: and 2.66 with a free grid tilt; the hand-held scan, 0.49 % / 0.88 %, 0.35 levels free and 1.0 without)
FREE_VISIBILITY = 0.004
#: the spread of the vignetting centre about the principal point in real lenses (half-diagonals; 0.05 is 20 px
#: at 640x480) and of a sensor-shading tilt of log V across the half-diagonal: what an open tilt is not known to
PLAUSIBLE_OFFSET = 0.05
PLAUSIBLE_TILT = 0.01
#: what usually makes a self-calibrated V implausible
CAUSES = ("lens-shading correction in the camera (turn it off or calibrate with it on), dust on the lens, "
          "specular surfaces, depth not registered to colour, a rolling shutter with fast motion")


@dataclass(frozen=True)
class TiltVisibility:
    """``visibility`` (x, y): the share of a tilt's information left when the exposures are fitted too (module
    doc); ``information`` (2, 2): the tilt's information with the exposures fitted (sum of weights times squared
    absorbed tilt, per unit tilt); ``open``: the axes whose tilt the data leave open."""

    visibility: tuple[float, float]
    information: np.ndarray
    open: tuple[bool, bool]

    def text(self) -> str | None:
        """One line when a tilt is open (None otherwise)."""
        axes = [a for a, o in zip(("left-right", "up-down"), self.open) if o]
        if not axes:
            return None
        seen = ", ".join(f"{a} {100 * v:.2f}%" for a, v in zip(("left-right", "up-down"), self.visibility))
        return (f"ambiguous: this sequence cannot pin a {' or '.join(axes)} tilt of V: exposure drift and the "
                f"surfaces' own brightness absorb it (what they leave of a tilt: {seen}; "
                f"{100 * OPEN_VISIBILITY:.2f}% needed); V's tilt is held at the plausible member (centred near the "
                "principal point) and its standard error includes the tilt left open; record turning back and forth "
                "and tilting up and down, or give the exposures (--exposures FILE)")

    def weak_text(self) -> str | None:
        """One note when an axis is seen, but weakly (below :data:`FREE_VISIBILITY` and not open; None otherwise):
        V's profile along it rests mostly on the polynomial's centre, and its standard error counts what that
        leaves open."""
        axes = [(a, v) for a, v, o in zip(("left-right", "up-down"), self.visibility, self.open)
                if not o and v < FREE_VISIBILITY]
        if not axes:
            return None
        seen = ", ".join(f"{a} {100 * v:.2f}%" for a, v in axes)
        both = len(axes) == 2
        motion = {"left-right": "turn the camera back and forth", "up-down": "tilt the camera up and down"}
        return (f"note: V's {' and '.join(a for a, _ in axes)} profile{'s are' if both else ' is'} seen weakly (what "
                f"the sequence leaves of a tilt: {seen}; {100 * FREE_VISIBILITY:.1f}% pins it): "
                f"{'they rest' if both else 'it rests'} mostly on the polynomial's centre and the standard error "
                "includes a sensor-shading tilt the data cannot exclude; "
                + " and ".join(motion[a] for a, _ in axes) + f" to pin {'them' if both else 'it'}")


def _absorb(field: np.ndarray, w: np.ndarray, point: np.ndarray, frame: np.ndarray, n_points: int,
            n_frames: int, fixed: np.ndarray) -> np.ndarray:
    """``field`` less its best weighted fit by radiances and exposures (the ``fixed`` frames' held)."""
    from radiometry.self_calibration_lsq import exposures_and_radiance as _exposures_and_radiance

    kappa, lp = _exposures_and_radiance(field, w, point, frame, n_points, n_frames, fixed, np.zeros(n_frames))
    return field - np.nan_to_num(kappa)[frame] - lp[point]


def tilt_visibility(x: np.ndarray, y: np.ndarray, w: np.ndarray, point: np.ndarray, frame: np.ndarray,
                    resolution: tuple[int, int], n_points: int, n_frames: int,
                    fixed: np.ndarray | None = None) -> TiltVisibility:
    """How much of a tilt of ``log V`` the sightings (``x``, ``y``, weights ``w``) can see (module doc)."""
    width, height = resolution
    radius = float(np.hypot(width / 2.0, height / 2.0))
    fixed = np.arange(n_frames) == 0 if fixed is None else fixed
    fields = [(np.asarray(x, float) - (width - 1) / 2) / radius, (np.asarray(y, float) - (height - 1) / 2) / radius]
    free = [_absorb(f, w, point, frame, n_points, n_frames, fixed) for f in fields]
    info = np.array([[np.sum(w * a * b) for b in free] for a in free])
    full = np.array([np.sum(w * (f - np.sum(w * f) / np.sum(w)) ** 2) for f in fields])
    vis = tuple(float(min(1.0, info[i, i] / max(full[i], 1e-300))) for i in range(2))
    return TiltVisibility(vis, info, tuple(v < OPEN_VISIBILITY for v in vis))


def tilt_stderr(vis: TiltVisibility, resolution: tuple[int, int], p: np.ndarray, axes=None) -> np.ndarray:
    """The standard error ``(H, W)`` of ``log V`` that an open tilt adds, for V's polynomial ``p`` (centre, b1..b3
    as :mod:`radiometry.self_calibration`): along each open axis, a vignetting centre :data:`PLAUSIBLE_OFFSET`
    off the one chosen (the slope of the fitted V, at least that of a quadratic with its outer fall-off, times
    that offset) and a sensor-shading tilt of
    :data:`PLAUSIBLE_TILT`; the data do not narrow either. ``axes``: the axes to count (default the open ones;
    the solver also counts those below :data:`FREE_VISIBILITY`, whose tilt rests on the polynomial's centre
    alone). On an axis the data pin, 0 (the solver's own covariance carries it)."""
    width, height = resolution
    radius = float(np.hypot(width / 2.0, height / 2.0))
    cx, cy, b1, b2, b3 = (float(v) for v in p[:5])
    xs = (np.arange(width) - cx)[None, :]
    ys = (np.arange(height) - cy)[:, None]
    r2 = (xs ** 2 + ys ** 2) / radius ** 2
    q = np.maximum(1 + b1 * r2 + b2 * r2 ** 2 + b3 * r2 ** 3, 1e-6)
    slope = (b1 + 2 * b2 * r2 + 3 * b3 * r2 ** 2) / q * 2 / radius ** 2      # d log V / d (r^2) * 2 / R^2
    # the fitted radial profile is itself uncertain where a tilt is open (a pan sees it along one axis only): the
    # slope is at least that of the quadratic with the fitted V's outer fall-off (log V = -a r^2, a from r^2 > 0.5)
    outer = r2 > 0.5
    if outer.any():
        a = float(np.max(-np.log(q[outer]) / r2[outer]))
        slope = -np.maximum(np.abs(slope), 2 * max(a, 0.0) / radius ** 2)
    var = np.zeros((height, width))
    for d, o in zip((xs, ys), vis.open if axes is None else axes):
        if o:
            var = var + (slope * d * PLAUSIBLE_OFFSET * radius) ** 2 + (PLAUSIBLE_TILT * d / radius) ** 2
    return np.sqrt(var)


def plausibility(v: np.ndarray, stderr: np.ndarray | None, centres, *, channels: str = "RGB",
                 rise: float = 0.02, blob: float = 0.03, min_area: float = 0.003) -> list[str]:
    """Sentences flagging an implausible ``v`` ``(H, W, C)`` (relative standard error ``stderr``, centres per
    channel): V brighter away from its centre (the ring medians rise outward by more than ``rise`` and two
    standard errors), or dark blobs inside the image (connected regions below the V around them by more than
    ``blob`` and three standard errors, larger than ``min_area`` of the image, not touching its border)."""
    import cv2

    h, w, n = v.shape
    notes = []
    for c in range(n):
        vc = v[:, :, c].astype(np.float64)
        se = np.zeros_like(vc) if stderr is None else stderr[:, :, c].astype(np.float64)
        cx, cy = centres[c]
        yy, xx = np.mgrid[0:h, 0:w]
        r = np.hypot(xx - cx, yy - cy)
        rings = np.minimum((r / (np.hypot(w, h) / 2) * 24).astype(np.int64), 24)
        counts = np.bincount(rings.ravel(), minlength=25)
        med = np.array([np.median(vc[rings == k]) if counts[k] > 20 else np.nan for k in range(25)])
        ring_se = np.array([np.median(se[rings == k]) if counts[k] > 20 else np.nan for k in range(25)])
        valid = np.flatnonzero(np.isfinite(med))
        centre_v = med[valid[0]]
        rises = [k for k in valid if med[k] - centre_v > max(rise, 2 * ring_se[k])]
        corner = float(np.mean([vc[:h // 20 + 1, :w // 20 + 1].mean(), vc[:h // 20 + 1, -(w // 20 + 1):].mean(),
                                vc[-(h // 20 + 1):, :w // 20 + 1].mean(), vc[-(h // 20 + 1):, -(w // 20 + 1):].mean()]))
        if rises:
            notes.append(f"V of {channels[c]} is brighter away from its centre than at it (ring median up to "
                         f"{100 * (np.nanmax(med) / centre_v - 1):.1f}% above the centre's; corner/centre "
                         f"{corner / centre_v:.2f}), which no lens does")
        # a blob is a local dip: below the V that a closing (a dark feature smaller than a sixth of the image
        # removed) and a blur leave; a smooth asymmetry of the whole V (a decentred lens) is not one
        size = max(3, (min(h, w) // 6) | 1)
        closed = cv2.morphologyEx(vc.astype(np.float32), cv2.MORPH_CLOSE,
                                  cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))
        background = cv2.GaussianBlur(closed, (0, 0), size / 4.0).astype(np.float64)
        dip = vc / np.maximum(background, 1e-6) - 1
        mask = ((dip < -blob) & (dip < -3 * se)).astype(np.uint8)
        n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        for k in range(1, n_lab):
            x0, y0, bw, bh, area = stats[k]
            inside = x0 > 0 and y0 > 0 and x0 + bw < w and y0 + bh < h
            if inside and area > min_area * h * w:
                depth = -float(dip[labels == k].min())
                notes.append(f"V of {channels[c]} has a dark blob inside the image ({100 * depth:.0f}% below the V "
                             f"around it, {100 * area / (h * w):.1f}% of the image around x={x0 + bw // 2}, "
                             f"y={y0 + bh // 2})")
                break
    if notes:
        notes.append(f"a lens does not do this; usual causes: {CAUSES}")
    return notes


__all__ = ["CAUSES", "OPEN_VISIBILITY", "PLAUSIBLE_TILT", "TiltVisibility", "plausibility", "tilt_stderr",
           "tilt_visibility"]
