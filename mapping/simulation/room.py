"""A furnished room with textured walls, generated from a seed; saved as parameters + seed.

World frame: ``z`` up, the floor at ``z = 0``, the room spanning ``[0, Lx] x [0, Ly] x [0, Lz]``.
Furniture boxes stand along the walls; the camera region (:attr:`Room.camera_bounds`) is the middle
of the room, at least ``clearance`` metres from every box and wall, so a trajectory inside it never
enters furniture and rarely sees anything closer than ~0.5 m.

Walls carry procedural textures (paint, wallpaper, tiles, generated posters and printed pages) and,
optionally, the user's own pictures (``pictures=(path, ...)``, PNG or JPEG; ``radiomap simulate room
--picture PATH``): each is pasted on a wall at eye level with its longer side 0.5-1.0 m and its aspect
ratio kept, its sRGB values decoded to linear albedo (:func:`mapping.simulation.textures.picture`).
Their placement is drawn from the room's random stream after everything else, so adding a picture
changes nothing else in the room.

``make_room(seed, **params)`` is deterministic: ``room.json`` stores the seed and parameters (plus
informational derived values and checksums) and :func:`load_room` rebuilds the identical room. Pictures
are recorded by absolute path with their SHA-1; one changed since is reported with the texture checksum
warning.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from mapping.simulation import textures as tx
from mapping.simulation.scene import Face, Lighting, PointLight, TexturedScene
from radiometry.errors import DatasetError, ImageError
from radiometry.fileio import atomic_write_json
from radiometry.images import read_rgb

log = logging.getLogger(__name__)

ROOM_FORMAT = "radiomap-room"
ROOM_FORMAT_VERSION = 1
_STREAM_ROOM = 101

_UP = np.array([0.0, 0.0, 1.0])
# warm, neutral and cool white lights (relative RGB)
_LIGHT_COLOURS = (np.array([1.0, 0.9, 0.74]), np.array([1.0, 0.97, 0.92]), np.array([0.9, 0.95, 1.0]))


@dataclass(frozen=True)
class RoomParams:
    """Parameters of :func:`make_room` (all but the seed).

    size:            room (Lx, Ly, Lz) metres.
    n_boxes:         furniture boxes along the walls (some get a smaller box stacked on top).
    n_lights:        point lights under the ceiling.
    n_posters:       generated pictures and printed pages pasted on the walls.
    texel:           texture resolution, metres per texel (5 mm resolves detail at ~1 px from 2.6 m
                     with a 640 x 480 Kinect-like camera).
    light_intensity: point light intensity (radiance units x m^2).
    ambient:         ambient irradiance.
    clearance:       free distance around the camera region.
    pictures:        paths of PNG/JPEG pictures pasted on the walls (stored as absolute paths; the
                     files are read by :func:`make_room`, and again by :func:`load_room`).
    """

    size: tuple = (6.0, 5.0, 2.7)
    n_boxes: int = 7
    n_lights: int = 2
    n_posters: int = 5
    texel: float = 0.005
    light_intensity: float = 1400.0
    ambient: float = 40.0
    clearance: float = 0.4
    pictures: tuple = ()

    def __post_init__(self) -> None:
        size = tuple(float(v) for v in self.size)
        if len(size) != 3 or size[0] < 3.2 or size[1] < 3.2 or size[2] < 2.2 or max(size) > 30:
            raise ValueError(f"size must be (Lx, Ly, Lz) metres with Lx, Ly >= 3.2, Lz >= 2.2 and at most 30, "
                             f"got {self.size!r}")
        object.__setattr__(self, "size", size)
        for name, lo, hi in (("n_boxes", 0, 30), ("n_lights", 0, 8), ("n_posters", 0, 30)):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and lo <= v <= hi):
                raise ValueError(f"{name} must be a whole number in {lo}..{hi}, got {v!r}")
        if not (0.001 <= self.texel <= 0.05):
            raise ValueError(f"texel must be within [0.001, 0.05] metres, got {self.texel!r}")
        if not (self.light_intensity >= 0 and self.ambient >= 0 and self.light_intensity + self.ambient > 0):
            raise ValueError("light_intensity and ambient must be >= 0 and not both 0")
        if not (0.1 <= self.clearance <= 1.0):
            raise ValueError(f"clearance must be within [0.1, 1] metres, got {self.clearance!r}")
        object.__setattr__(self, "pictures", _picture_paths(self.pictures))


def _picture_paths(pictures: Any) -> tuple[str, ...]:
    """``pictures`` as a tuple of absolute path strings, or a ValueError saying what is wrong."""
    if isinstance(pictures, (str, bytes, os.PathLike)):
        raise ValueError(f"pictures must be a sequence of image paths, got the single path {pictures!r}; "
                         f"write pictures=({str(pictures)!r},)")
    try:
        paths = tuple(os.fspath(v) for v in pictures)
    except TypeError:
        raise ValueError(f"pictures must be a sequence of image paths (str or pathlib.Path), "
                         f"got {pictures!r}") from None
    if any(not isinstance(v, str) or not v.strip() for v in paths):
        raise ValueError(f"pictures must be non-empty path strings, got {paths!r}")
    if len(paths) > 30:
        raise ValueError(f"pictures: at most 30 pictures, got {len(paths)}")
    return tuple(os.path.abspath(os.path.expanduser(v)) for v in paths)


@dataclass(frozen=True)
class PicturePlacement:
    """Where :func:`make_room` pasted a user picture: the wall face, the texel rectangle in its texture
    (row ``top``, column ``left``, ``height`` x ``width`` texels; row 0 is the top of the wall), and the
    SHA-1 of the file it read."""

    path: str
    face: str
    top: int
    left: int
    height: int
    width: int
    sha1: str


@dataclass(frozen=True)
class Box:
    """A furniture box: footprint centre, size (along its own x, y, z), yaw and base height."""

    centre: tuple[float, float]
    size: tuple[float, float, float]
    yaw: float
    base: float
    material: str

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([c, s, 0.0]), np.array([-s, c, 0.0])

    def footprint_aabb(self, margin: float = 0.0) -> tuple[float, float, float, float]:
        ex, ey = self.axes()
        hx = abs(ex[0]) * self.size[0] / 2 + abs(ey[0]) * self.size[1] / 2 + margin
        hy = abs(ex[1]) * self.size[0] / 2 + abs(ey[1]) * self.size[1] / 2 + margin
        return (self.centre[0] - hx, self.centre[0] + hx, self.centre[1] - hy, self.centre[1] + hy)

    def corners(self) -> np.ndarray:
        """The 8 corners (8, 3): bottom four then top four."""
        ex, ey = self.axes()
        c = np.array([self.centre[0], self.centre[1], self.base])
        out = []
        for z in (0.0, self.size[2]):
            for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                out.append(c + sx * ex * self.size[0] / 2 + sy * ey * self.size[1] / 2 + _UP * z)
        return np.array(out)


class Room(TexturedScene):
    """A :class:`TexturedScene` made by :func:`make_room`, with its seed, parameters, furniture
    (:attr:`boxes`) and the region a camera may move in (:attr:`camera_bounds`)."""

    def __init__(self, faces: list[Face], lighting: Lighting, *, seed: int, params: RoomParams,
                 boxes: list[Box], camera_bounds: tuple[np.ndarray, np.ndarray],
                 pictures: list[PicturePlacement] | tuple = ()) -> None:
        super().__init__(faces, lighting, name=f"room-{seed}")
        self.seed = int(seed)
        self.params = params
        self.boxes = list(boxes)
        self.pictures = list(pictures)
        self.camera_bounds = (np.asarray(camera_bounds[0], float), np.asarray(camera_bounds[1], float))

    @property
    def size(self) -> tuple[float, float, float]:
        return self.params.size

    def centre(self) -> np.ndarray:
        return np.array(self.params.size) / 2.0

    def to_dict(self) -> dict[str, Any]:
        """What ``room.json`` holds: seed + parameters (enough to rebuild), and for information the
        furniture, lights, camera region, user pictures (where they went, their SHA-1) and checksums of
        geometry and textures."""
        return {
            "format": ROOM_FORMAT, "version": ROOM_FORMAT_VERSION, "seed": self.seed,
            "params": {f.name: (list(v) if isinstance(v := getattr(self.params, f.name), tuple) else v)
                       for f in fields(self.params)},
            "boxes": [asdict(b) for b in self.boxes],
            "pictures": [asdict(pl) for pl in self.pictures],
            "lighting": self.lighting.to_dict(),
            "camera_bounds": [self.camera_bounds[0].tolist(), self.camera_bounds[1].tolist()],
            "faces": [{"name": f.name, "origin": f.origin.tolist(), "axis_s": f.axis_s.tolist(),
                       "axis_t": f.axis_t.tolist(), "size": list(f.size),
                       "texture_shape": list(f.texture.shape[:2])} for f in self.faces],
            "checksum": {"geometry": self.checksum(textures=False), "textures": self.checksum(textures=True)},
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write ``room.json`` atomically."""
        return atomic_write_json(path, self.to_dict())


def load_room(path: str | os.PathLike) -> Room:
    """Rebuild the room described by a ``room.json`` written by :meth:`Room.save`.

    Raises :class:`DatasetError` when the file is not a room description, a picture it names cannot
    be read, or the rebuilt geometry differs from the recorded checksum (a different radiomap version);
    a texture checksum mismatch (possible across CPU instruction sets, or a picture file changed since)
    is logged as a warning naming the changed pictures.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such room description; it is written as truth/room.json by "
                           "'radiomap simulate room'")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc}); re-create the sequence") from None
    if not isinstance(data, dict) or data.get("format") != ROOM_FORMAT:
        raise DatasetError(f"{path}: not a radiomap room description (format {data.get('format')!r})"
                           if isinstance(data, dict) else f"{path}: not a radiomap room description")
    if data.get("version") != ROOM_FORMAT_VERSION:
        raise DatasetError(f"{path}: room format version {data.get('version')!r} is not supported "
                           f"(this radiomap reads {ROOM_FORMAT_VERSION}); upgrade radiomap")
    try:
        room = make_room(int(data["seed"]), **data["params"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: bad room parameters ({exc}); re-create the sequence") from None
    except ImageError as exc:
        raise DatasetError(f"{path}: cannot rebuild the room: {exc}") from None
    checks = data.get("checksum", {})
    if checks.get("geometry") and checks["geometry"] != room.checksum(textures=False):
        raise DatasetError(f"{path}: the rebuilt room geometry differs from the recorded one (written by "
                           "another radiomap version?); re-create the sequence with this version")
    recorded = {d.get("path"): d.get("sha1") for d in data.get("pictures", []) if isinstance(d, dict)}
    changed = [pl.path for pl in room.pictures if recorded.get(pl.path, pl.sha1) != pl.sha1]
    if changed:
        log.warning("%s: rebuilt textures differ from the recorded checksum: picture(s) changed since the room "
                    "was made: %s", path, ", ".join(changed))
    elif checks.get("textures") and checks["textures"] != room.checksum(textures=True):
        log.warning("%s: rebuilt textures differ slightly from the recorded checksum", path)
    return room


# ------------------------------------------------------------------------------------- generation
def _wall_frames(L: tuple[float, float, float]) -> list[tuple[str, np.ndarray, np.ndarray, float]]:
    """(name, origin, axis_s, length) of the four walls, each seen from inside with t = up."""
    lx, ly, _ = L
    return [
        ("wall_south", np.array([lx, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]), lx),
        ("wall_east", np.array([lx, ly, 0.0]), np.array([0.0, -1.0, 0.0]), ly),
        ("wall_north", np.array([0.0, ly, 0.0]), np.array([1.0, 0.0, 0.0]), lx),
        ("wall_west", np.array([0.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), ly),
    ]


def _grid(size: tuple[float, float], texel: float) -> tuple[int, int]:
    """(h, w) texels covering a face of (s, t) size."""
    return max(2, int(math.ceil(size[1] / texel))), max(2, int(math.ceil(size[0] / texel)))


def _box_faces(box: Box, rng: np.random.Generator, texel: float, index: int) -> list[Face]:
    ex, ey = box.axes()
    sx, sy, sz = box.size
    c = np.array([box.centre[0], box.centre[1], box.base])
    sides = [(ex, sx / 2, sy), (-ex, sx / 2, sy), (ey, sy / 2, sx), (-ey, sy / 2, sx)]
    faces = []
    image_side = int(rng.integers(0, 4)) if rng.random() < 0.5 else -1
    for k, (n, half, width) in enumerate(sides):
        s_axis = np.cross(_UP, n)
        origin = c + n * half - s_axis * width / 2
        h, w = _grid((width, sz), texel)
        if k == image_side:
            tex = tx.poster(rng, h, w, texel)
        else:
            tex = tx.material(rng, h, w, texel, box.material)
            if rng.random() < 0.3 and min(width, sz) > 0.25:
                ph, pw = _grid((0.148, 0.21), texel)   # an A5 label
                tx.paste(tex, tx.printed_page(rng, ph, pw, texel), int(rng.integers(0, max(1, h - ph))),
                         int(rng.integers(0, max(1, w - pw))))
        faces.append(Face(f"box{index}_side{k}", origin, s_axis, _UP, (width, sz), tex))
    top_origin = c + _UP * sz - ex * sx / 2 - ey * sy / 2
    h, w = _grid((sx, sy), texel)
    top_kind = "granite" if box.material in ("paint", "page") else box.material
    faces.append(Face(f"box{index}_top", top_origin, ex, ey, (sx, sy), tx.material(rng, h, w, texel, top_kind)))
    return faces


def _read_picture(path: str) -> tuple[np.ndarray, str]:
    """A user picture as RGB uint8 (grey stays 2-D) and the SHA-1 of its file; :class:`ImageError`
    naming the file when it is missing or not a readable image."""
    file = Path(path)
    if not file.is_file():
        raise ImageError(f"{file}: no such picture for the room; check the path (--picture / RoomParams.pictures)")
    try:
        rgb = read_rgb(file)
        digest = hashlib.sha1(file.read_bytes()).hexdigest()
    except ImageError as exc:
        raise ImageError(f"room picture {exc}; use a PNG or JPEG file") from None
    except OSError as exc:
        raise ImageError(f"{file}: cannot read the room picture ({exc.strerror or exc}); check its "
                         "permissions") from None
    return rgb, digest


def _paste_picture(path: str, walls: list[Face], rng: np.random.Generator, p: RoomParams) -> PicturePlacement:
    """Paste one user picture on a wall at eye level, its longer side 0.5-1.0 m. Always draws the same
    four numbers from ``rng``, so the picture's content never changes the rest of the room."""
    rgb, digest = _read_picture(path)
    k = int(rng.integers(0, 4))
    longer = rng.uniform(0.5, 1.0)
    centre_height = rng.uniform(1.3, 1.8)
    along = rng.random()
    wall = walls[k]
    th, tw = wall.texture.shape[:2]
    ih, iw = rgb.shape[:2]
    texel = p.texel
    n_long = max(2, int(round(longer / texel)))
    n_short = max(2, int(round(n_long * min(ih, iw) / max(ih, iw))))
    ph, pw = (n_long, n_short) if ih > iw else (n_short, n_long)
    lz = p.size[2]
    top_m = min(lz - 0.05, max(centre_height + ph * texel / 2, 0.1 + ph * texel))   # above the skirting board
    top = int(round((lz - top_m) / texel))
    left = int(round(along * max(0, tw - pw)))
    tx.paste(wall.texture, tx.picture(rgb, ph, pw), top, left)
    return PicturePlacement(path, wall.name, top, left, ph, pw, digest)


def _overlaps(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> bool:
    return a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]


def _place_boxes(rng: np.random.Generator, p: RoomParams) -> tuple[list[Box], float]:
    """Boxes along the walls; returns them and the depth of the furniture band."""
    lx, ly, lz = p.size
    band = 1.0  # furniture stays within this distance of its wall
    walls = _wall_frames(p.size)
    inward = [np.array([0.0, 1.0]), np.array([-1.0, 0.0]), np.array([0.0, -1.0]), np.array([1.0, 0.0])]
    kinds = ["planks", "granite", "checker", "stripes", "paint", "tiles", "page"]
    boxes: list[Box] = []
    for i in range(p.n_boxes):
        for _attempt in range(60):
            k = int(rng.integers(0, 4))
            _, origin, s_axis, length = walls[k]
            width = rng.uniform(0.4, 1.4)
            depth = rng.uniform(0.3, 0.65)
            height = float(rng.choice([rng.uniform(0.35, 0.6), 0.75, rng.uniform(0.9, 1.45)]))
            jitter = math.radians(rng.uniform(-7, 7))
            n2 = inward[k]
            yaw = math.atan2(n2[1], n2[0]) + jitter      # box x axis along the inward normal
            half_n = depth / 2 * abs(math.cos(jitter)) + width / 2 * abs(math.sin(jitter))
            gap = rng.uniform(0.03, 0.12)
            along = rng.uniform(0.1 + width / 2, length - 0.1 - width / 2)
            foot = origin[:2] + s_axis[:2] * along + n2 * (gap + half_n)
            box = Box((float(foot[0]), float(foot[1])), (depth, width, height), yaw, 0.0,
                      str(kinds[int(rng.integers(0, len(kinds)))]))
            aabb = box.footprint_aabb()
            inside = aabb[0] > 0.02 and aabb[1] < lx - 0.02 and aabb[2] > 0.02 and aabb[3] < ly - 0.02
            if inside and not any(_overlaps(box.footprint_aabb(0.05), b.footprint_aabb()) for b in boxes
                                  if b.base == 0.0):
                boxes.append(box)
                if height < 1.1 and rng.random() < 0.4:   # something standing on it
                    w2, d2 = rng.uniform(0.15, min(0.45, width * 0.8)), rng.uniform(0.12, min(0.35, depth * 0.8))
                    h2 = rng.uniform(0.08, 0.35)
                    ex, ey = box.axes()
                    ox = rng.uniform(-(depth - d2) / 2, (depth - d2) / 2)
                    oy = rng.uniform(-(width - w2) / 2, (width - w2) / 2)
                    c2 = np.array(box.centre) + ex[:2] * ox + ey[:2] * oy
                    boxes.append(Box((float(c2[0]), float(c2[1])), (d2, w2, h2), yaw, height,
                                     str(kinds[int(rng.integers(0, len(kinds)))])))
                break
        else:
            log.info("room: could not place furniture box %d without overlap; the room has %d boxes", i, len(boxes))
    return boxes, band


def make_room(seed: int = 0, **params: Any) -> Room:
    """Generate a furnished, textured, lit room from ``seed`` and :class:`RoomParams` fields."""
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative whole number, got {seed!r}")
    known = {f.name for f in fields(RoomParams)}
    unknown = set(params) - known
    if unknown:
        raise ValueError(f"unknown room parameters {sorted(unknown)}; valid: {sorted(known)}")
    p = RoomParams(**params)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _STREAM_ROOM]))
    lx, ly, lz = p.size
    texel = p.texel
    faces: list[Face] = []

    # floor and ceiling
    h, w = _grid((lx, ly), texel)
    floor_kind = "planks" if rng.random() < 0.6 else "tiles"
    faces.append(Face("floor", [0, 0, 0], [1, 0, 0], [0, 1, 0], (lx, ly), tx.material(rng, h, w, texel, floor_kind)))
    ceiling_tex = tx.paint(rng, h, w, texel, np.array([0.82, 0.82, 0.8]), variation=0.03)
    faces.append(Face("ceiling", [0, 0, lz], [0, 1, 0], [1, 0, 0], (ly, lx),
                      np.ascontiguousarray(ceiling_tex.transpose(1, 0, 2))))

    # walls: paint, wallpaper stripes, more paint, a half-tiled wall; skirting boards; pictures
    wall_kinds = ["paint", "stripes", "paint", "tiles"]
    order = rng.permutation(4)
    for j, (name, origin, s_axis, length) in enumerate(_wall_frames(p.size)):
        h, w = _grid((length, lz), texel)
        kind = wall_kinds[int(order[j])]
        if kind == "tiles":
            tex = tx.paint(rng, h, w, texel, tx.random_colour(rng, 0.55, 0.85, 0.2))
            th = int(h * rng.uniform(0.35, 0.5))
            tex[h - th:] = tx.material(rng, th, w, texel, "tiles")
        elif kind == "stripes":
            c = tx.random_colour(rng, 0.5, 0.8, 0.3)
            tex = tx.stripes(rng, h, w, texel, np.stack([c, c * 0.7]), rng.uniform(0.08, 0.2), np.pi / 2)
        else:
            tex = tx.paint(rng, h, w, texel, tx.random_colour(rng, 0.45, 0.85, 0.3))
        skirting = max(2, int(round(0.08 / texel)))
        tex[h - skirting:] = tx.paint(rng, skirting, w, texel, np.array([0.12, 0.1, 0.09]), 0.05)
        faces.append(Face(name, origin, s_axis, [0, 0, 1], (length, lz), tex))

    walls = faces[2:6]
    for _ in range(p.n_posters):
        wall = walls[int(rng.integers(0, 4))]
        h, w = wall.texture.shape[:2]
        if rng.random() < 0.65:
            ph, pw = _grid((rng.uniform(0.4, 1.1), rng.uniform(0.35, 0.8)), texel)
            patch = tx.poster(rng, ph, pw, texel)
        else:
            ph, pw = _grid((0.21, 0.297), texel)
            patch = tx.printed_page(rng, ph, pw, texel)
        top = int((lz - rng.uniform(1.3, 2.1)) / texel)
        left = int(rng.integers(0, max(1, w - pw)))
        tx.paste(wall.texture, patch, top, left)

    boxes, band = _place_boxes(rng, p)
    for i, box in enumerate(boxes):
        faces.extend(_box_faces(box, rng, texel, i))

    # lights under the ceiling, away from the walls
    lights = []
    for _ in range(p.n_lights):
        pos = (rng.uniform(1.0, lx - 1.0), rng.uniform(1.0, ly - 1.0), lz - rng.uniform(0.3, 0.6))
        colour = _LIGHT_COLOURS[int(rng.integers(0, len(_LIGHT_COLOURS)))]
        intensity = p.light_intensity * rng.uniform(0.7, 1.3) * colour
        lights.append(PointLight(tuple(float(v) for v in pos), tuple(float(v) for v in intensity), 1.0))
    amb_tint = np.array([1.0, 0.98, 0.95])
    lighting = Lighting(tuple(float(v) for v in p.ambient * amb_tint), 0.25, tuple(lights))

    # the user's pictures last: the rest of the room is the same with or without them
    pictures = [_paste_picture(path, walls, rng, p) for path in p.pictures]

    margin = band + p.clearance
    lo = np.array([margin, margin, 1.1])
    hi = np.array([lx - margin, ly - margin, min(1.75, lz - 0.6)])
    return Room(faces, lighting, seed=int(seed), params=p, boxes=boxes, camera_bounds=(lo, hi), pictures=pictures)
