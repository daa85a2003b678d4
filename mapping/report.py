"""Figures, mesh renders and the self-contained HTML report of a comparison (:mod:`mapping.compare`).

- :func:`raycast_colours`: a vertex-coloured triangle mesh rendered from a camera pose on the CPU: Open3D's
  ``RaycastingScene`` finds the first triangle hit by each pixel's ray and the colour is interpolated from
  the triangle's three vertex colours with the hit's barycentric ``(u, v)`` (hit = ``(1-u-v) v0 + u v1 +
  v v2``, Open3D's convention). No shading: the pixels show the map's colours exactly as stored (in display
  levels), which is what a comparison of radiometric corrections is about.
- :func:`render_scene_truth`: the simulated scene's true radiance from the same viewpoint, for reference.
- :func:`pick_viewpoints`: 2-3 poses spread along a trajectory.
- :func:`save_render_grid`: views x methods side by side in one PNG.
- :func:`write_html_report`: one HTML file with every figure embedded as a base64 PNG (it opens anywhere,
  alone or moved) and relative links to the meshes and tables beside it.

Images are uint8 RGB ``(H, W, 3)``; poses camera-to-world ``(4, 4)``; ``K`` the ``(3, 3)`` pinhole matrix.
"""

from __future__ import annotations

import base64
import html
import logging
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.errors import OutputError
from mapping.figure_files import save_figure
from radiometry.fileio import atomic_write_text

log = logging.getLogger(__name__)

BACKGROUND = (40, 40, 46)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------------------------------
# rendering
# --------------------------------------------------------------------------------------------------
def _check_view(pose: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"pose must be a finite (4, 4) camera-to-world matrix, got shape {pose.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"K must be a (3, 3) pinhole matrix with positive focal lengths, got {K.tolist()}")
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"width and height must be positive, got {width} x {height}")
    return pose, K


def camera_rays(pose: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Rays ``(H, W, 6)`` float32 (origin, unit direction in world coordinates) through the pixel centres of
    a pinhole camera at ``pose`` (OpenCV axes: x right, y down, z forward)."""
    pose, K = _check_view(pose, K, width, height)
    u, v = np.meshgrid(np.arange(int(width), dtype=np.float64), np.arange(int(height), dtype=np.float64))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    d = d_cam @ pose[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    origin = np.broadcast_to(pose[:3, 3], d.shape)
    return np.concatenate([origin, d], axis=-1).astype(np.float32)


class MeshRaycaster:
    """A triangle mesh with per-vertex uint8 colours, ready to be rendered from many poses."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray) -> None:
        from mapping._open3d import o3d

        v = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
        t = np.asarray(triangles).reshape(-1, 3)
        c = np.asarray(colours)
        if c.shape != v.shape:
            raise ValueError(f"colours must be (N, 3) like the vertices {v.shape}, got {c.shape}")
        if t.size and (t.min() < 0 or t.max() >= len(v)):
            raise ValueError(f"triangles index vertices 0..{len(v) - 1}, got indices in [{t.min()}, {t.max()}]")
        self.vertices = v
        self.triangles = t.astype(np.int64)
        self.colours = c.astype(np.float32)
        self._scene = None
        if len(v) and len(t):
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(v)),
                                o3d.core.Tensor(np.ascontiguousarray(t, dtype=np.uint32)))
            self._scene = scene

    @property
    def empty(self) -> bool:
        return self._scene is None

    def cast(self, rays: np.ndarray) -> dict[str, np.ndarray]:
        """``t_hit`` (inf on a miss), ``primitive_ids`` (int64, -1 on a miss), ``primitive_uvs``."""
        from mapping._open3d import o3d

        shape = rays.shape[:-1]
        if self._scene is None:
            return {"t_hit": np.full(shape, np.inf, np.float32), "primitive_ids": np.full(shape, -1, np.int64),
                    "primitive_uvs": np.zeros(shape + (2,), np.float32)}
        ans = self._scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)))
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        prim[prim == np.iinfo(np.uint32).max] = -1
        return {"t_hit": ans["t_hit"].numpy(), "primitive_ids": prim, "primitive_uvs": ans["primitive_uvs"].numpy()}

    def render(self, pose: np.ndarray, K: np.ndarray, width: int, height: int, *,
               background: Sequence[int] = BACKGROUND) -> np.ndarray:
        """uint8 RGB ``(height, width, 3)``: vertex colours interpolated barycentrically at each ray's first
        hit; ``background`` where the ray misses the mesh."""
        hit = self.cast(camera_rays(pose, K, width, height))
        prim = hit["primitive_ids"]
        out = np.empty((int(height), int(width), 3), np.float32)
        out[...] = np.asarray(background, np.float32)
        ok = prim >= 0
        if np.any(ok):
            tri = self.triangles[prim[ok]]
            uv = hit["primitive_uvs"][ok]
            w0 = (1.0 - uv[:, 0] - uv[:, 1])[:, None]
            c = self.colours
            out[ok] = w0 * c[tri[:, 0]] + uv[:, 0:1] * c[tri[:, 1]] + uv[:, 1:2] * c[tri[:, 2]]
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def raycast_colours(vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray, pose: np.ndarray,
                    K: np.ndarray, width: int, height: int, *, background: Sequence[int] = BACKGROUND) -> np.ndarray:
    """Render a vertex-coloured mesh from ``pose`` (see :class:`MeshRaycaster`); uint8 RGB ``(H, W, 3)``."""
    return MeshRaycaster(vertices, triangles, colours).render(pose, K, width, height, background=background)


def render_scene_truth(scene, pose: np.ndarray, K: np.ndarray, width: int, height: int,
                       to_display: Callable[[np.ndarray], np.ndarray], *,
                       background: Sequence[int] = BACKGROUND) -> np.ndarray:
    """The true radiance of a simulated scene (:class:`mapping.simulation.scene.TexturedScene`) seen from
    ``pose``, mapped to display levels by ``to_display`` ((N, 3) radiance -> (N, 3) levels); uint8 RGB."""
    rays = camera_rays(pose, K, width, height).reshape(-1, 6)
    hit = scene.cast(rays)
    prim = hit["primitive_ids"]
    out = np.empty((rays.shape[0], 3), np.float32)
    out[:] = np.asarray(background, np.float32)
    ok = prim >= 0
    if np.any(ok):
        faces, coords = scene.hit_coordinates(prim[ok], hit["primitive_uvs"][ok])
        radiance = scene.radiance_on_faces(faces, coords)
        out[ok] = np.asarray(to_display(radiance), dtype=np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8).reshape(int(height), int(width), 3)


def pick_viewpoints(poses: np.ndarray, n: int = 3, *, metres_per_radian: float = 1.0) -> list[int]:
    """Indices (ascending) of ``n`` distinct poses of a trajectory that see it from views as different as
    possible: the middle pose first, then greedily the pose farthest from those chosen, the distance between
    two poses being the angle between their optical axes (radians) plus their distance over
    ``metres_per_radian``. Deterministic."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (N, 4, 4), got shape {poses.shape}")
    if n < 1:
        raise ValueError(f"n must be at least 1, got {n}")
    count = poses.shape[0]
    if count == 0:
        return []
    axes = poses[:, :3, 2] / np.maximum(np.linalg.norm(poses[:, :3, 2], axis=1, keepdims=True), 1e-12)
    centres = poses[:, :3, 3]

    def distance(i: int) -> np.ndarray:
        angle = np.arccos(np.clip(axes @ axes[i], -1.0, 1.0))
        return angle + np.linalg.norm(centres - centres[i], axis=1) / metres_per_radian

    chosen = [count // 2]
    nearest = distance(chosen[0])
    while len(chosen) < min(n, count):
        nxt = int(np.argmax(nearest))
        if nearest[nxt] <= 0:
            break
        chosen.append(nxt)
        nearest = np.minimum(nearest, distance(nxt))
    return sorted(chosen)


def scaled_intrinsics(K: np.ndarray, width: int, height: int, new_width: int) -> tuple[np.ndarray, int, int]:
    """``K`` for the same field of view at ``new_width`` pixels (height scaled alike); returns ``(K, w, h)``."""
    s = float(new_width) / float(width)
    new_height = max(1, int(round(height * s)))
    K2 = np.array(K, dtype=np.float64, copy=True)
    K2[0, 0] *= s
    K2[1, 1] *= s
    K2[0, 2] = (K[0, 2] + 0.5) * s - 0.5
    K2[1, 2] = (K[1, 2] + 0.5) * s - 0.5
    return K2, int(new_width), new_height


# --------------------------------------------------------------------------------------------------
# figures
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GridLayout:
    """Where :func:`save_render_grid` puts things (pixels): one row per method (its label on the left), one
    column per view (its label on top), tiles enlarged ``scale`` times (nearest neighbour) so that a grid of
    small renders still fills the report's width."""

    rows: int
    columns: int
    tile_width: int            # of the renders, before scaling
    tile_height: int
    scale: int
    label_width: int
    title_height: int
    gap: int = 4

    @property
    def width(self) -> int:
        return self.label_width + self.columns * (self.tile_width * self.scale + self.gap)

    @property
    def height(self) -> int:
        return self.title_height + self.rows * (self.tile_height * self.scale + self.gap)

    def tile(self, row: int, column: int) -> tuple[int, int, int, int]:
        """``(x, y, width, height)`` of a tile from the image's top-left corner."""
        w, h = self.tile_width * self.scale, self.tile_height * self.scale
        return (self.label_width + column * (w + self.gap), self.title_height + row * (h + self.gap), w, h)


#: a render grid is enlarged (by a whole factor) until its tiles span at least this many pixels
GRID_MIN_WIDTH = 900
GRID_FONT_PX = 15


def render_grid_layout(rows: int, columns: int, tile_width: int, tile_height: int, *, title: bool = False
                       ) -> GridLayout:
    """The :class:`GridLayout` of ``rows`` methods x ``columns`` views of ``tile_width x tile_height`` renders."""
    scale = max(1, -(-GRID_MIN_WIDTH // max(1, columns * tile_width)))
    scale = min(scale, 4)
    return GridLayout(rows, columns, int(tile_width), int(tile_height), scale, label_width=190,
                      title_height=(2 * GRID_FONT_PX + 8) * (2 if title else 1))


def save_render_grid(path: str | os.PathLike, columns: Mapping[str, Sequence[np.ndarray]], *,
                     row_labels: Sequence[str] | None = None, title: str | None = None, dpi: int = 100) -> Path:
    """Renders side by side: one row per entry of ``columns`` (``{method label: [image per view]}``, its label
    on the left, wrapped) and one column per view (``row_labels`` above them), laid out by
    :func:`render_grid_layout`: tiles at their pixel size or enlarged by a whole factor (nearest neighbour), so
    that the grid fills a report's width; text 15 px. Written atomically (PNG, or JPEG for a ``.jpg`` path)."""
    import textwrap

    from matplotlib.figure import Figure

    if not columns:
        raise ValueError("columns must hold at least one method's renders")
    counts = {len(v) for v in columns.values()}
    if len(counts) != 1 or 0 in counts:
        raise ValueError(f"every column must have the same number (> 0) of views, got {sorted(counts)}")
    n_views = counts.pop()
    first = np.asarray(next(iter(columns.values()))[0])
    h, w = first.shape[:2]
    layout = render_grid_layout(len(columns), n_views, w, h, title=bool(title))
    fig = Figure(figsize=(layout.width / dpi, layout.height / dpi), dpi=dpi, facecolor="white")
    points = GRID_FONT_PX * 72.0 / dpi

    def at(x: float, y: float) -> tuple[float, float]:   # pixels from the top-left -> figure fraction
        return x / layout.width, 1.0 - y / layout.height

    for r, (label, images) in enumerate(columns.items()):
        for c, img in enumerate(images):
            img = np.asarray(img)
            if img.shape[:2] != (h, w):
                raise ValueError(f"every render must be {w}x{h} like the first, got {img.shape[1]}x{img.shape[0]} "
                                 f"({label}, view {c + 1})")
            big = np.repeat(np.repeat(img, layout.scale, axis=0), layout.scale, axis=1)
            x, y, tw, th = layout.tile(r, c)
            fig.figimage(big, xo=x, yo=layout.height - y - th, origin="upper")
        x, y, tw, th = layout.tile(r, 0)
        wrapped = textwrap.fill(str(label), width=max(8, int(layout.label_width / (0.62 * GRID_FONT_PX))))
        fig.text(*at(8, y + th / 2), wrapped, ha="left", va="center", fontsize=points)
    for c in range(n_views):
        x, y, tw, th = layout.tile(0, c)
        text = str(row_labels[c]) if row_labels is not None and c < len(row_labels) else f"view {c + 1}"
        fig.text(*at(x + tw / 2, y - 6), text, ha="center", va="bottom", fontsize=points)
    if title:
        fig.text(*at(layout.width / 2, 6), str(title), ha="center", va="top", fontsize=points * 1.15)
    return save_figure(fig, path, dpi=dpi)


def save_bar_chart(path: str | os.PathLike, values: Mapping[str, float], *, ylabel: str, title: str | None = None
                   ) -> Path:
    """A bar chart (one bar per method, its value above it inside the frame), drawn for a report's width."""
    from matplotlib.figure import Figure

    from mapping.plots import COLOURS, DPI, FULL_WIDTH_INCHES

    fig = Figure(figsize=(FULL_WIDTH_INCHES, 4.0))
    ax = fig.subplots()
    names = list(values)
    heights = [float(values[n]) for n in names]
    bars = ax.bar(range(len(names)), heights, color=COLOURS[0])
    ax.bar_label(bars, labels=[f"{v:.2f}" if math.isfinite(v) else "" for v in heights], padding=3, fontsize=11)
    finite = [v for v in heights if math.isfinite(v)]
    if finite and max(finite) > 0:
        ax.set_ylim(0, 1.15 * max(finite))   # room for the labels above the tallest bar
    ax.set_xticks(range(len(names)), names, fontsize=11)
    ax.set_ylabel(ylabel, fontsize=11)
    ax.grid(True, axis="y", alpha=0.3)
    if title:
        ax.set_title(title, fontsize=13)
    fig.tight_layout()
    return save_figure(fig, path, dpi=DPI)


# --------------------------------------------------------------------------------------------------
# HTML
# --------------------------------------------------------------------------------------------------
@dataclass
class ReportFigure:
    """A PNG (or JPEG) file to embed, with a caption."""

    path: Path
    caption: str = ""


@dataclass
class ReportTable:
    """A table: rows of ``{column: value}``; ``columns`` picks and orders them (default: the first row's)."""

    title: str
    rows: list[dict[str, Any]]
    columns: list[str] | None = None
    note: str = ""


@dataclass
class ReportSection:
    """A heading with paragraphs of plain text (escaped), tables and figures, in that order."""

    heading: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[ReportTable] = field(default_factory=list)
    figures: list[ReportFigure] = field(default_factory=list)
    links: list[tuple[str, str]] = field(default_factory=list)   # (text, path relative to the report)


_CSS = """
body { font-family: system-ui, -apple-system, 'Segoe UI', sans-serif; margin: 2em auto; max-width: 1240px;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; } h2 { font-size: 1.25em; margin-top: 1.8em;
       border-bottom: 1px solid #ddd; padding-bottom: 0.2em; }
.meta { color: #666; font-size: 0.9em; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.7em; text-align: left; vertical-align: top; }
th { background: #f3f3f6; } th.num, td.num { text-align: right; }
figure { margin: 1em 0; } figure img { width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { color: #444; font-size: 0.9em; margin-top: 0.3em; }
code { background: #f4f4f4; padding: 0 0.2em; }
"""


def _cell(value: Any) -> str:
    if isinstance(value, float):
        if not math.isfinite(value):
            return "-"
        if value.is_integer() and abs(value) < 1e6:
            return str(int(value))
        return f"{value:.3g}" if abs(value) >= 1000 or (value != 0 and abs(value) < 0.01) else f"{value:.2f}"
    if value is None:
        return "-"
    return html.escape(str(value))


def _numeric_column(values: Sequence[Any]) -> bool:
    """Numbers (and blanks: None, "-") only: right-aligned; a column with any text is left-aligned."""
    numbers = [v for v in values if v is not None and v != "-"]
    return bool(numbers) and all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                                 for v in numbers)


def _table_html(table: ReportTable) -> str:
    if not table.rows:
        return f"<p><em>{html.escape(table.title)}: no rows</em></p>"
    columns = table.columns or list(table.rows[0].keys())
    kind = {c: " class='num'" if _numeric_column([r.get(c) for r in table.rows]) else "" for c in columns}
    head = "".join(f"<th{kind[c]}>{html.escape(str(c))}</th>" for c in columns)
    body = "\n".join("<tr>" + "".join(f"<td{kind[c]}>{_cell(r.get(c))}</td>" for c in columns) + "</tr>"
                     for r in table.rows)
    note = f"<p class='meta'>{html.escape(table.note)}</p>" if table.note else ""
    title = f"<h3>{html.escape(table.title)}</h3>" if table.title else ""
    return f"{title}<table>\n<tr>{head}</tr>\n{body}\n</table>{note}"


def image_data_uri(path: str | os.PathLike) -> str:
    """``data:image/png;base64,...`` (or jpeg) of an image file; raises :class:`OutputError` if it is missing."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise OutputError(f"cannot embed {path} in the report: {exc.strerror or exc}") from None
    mime = "image/png" if data.startswith(PNG_SIGNATURE) else "image/jpeg" if data[:3] == b"\xff\xd8\xff" else None
    if mime is None:
        raise OutputError(f"cannot embed {path} in the report: not a PNG or JPEG image")
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def _relative(path: str | os.PathLike, base: Path) -> str:
    try:
        return Path(os.path.relpath(Path(path).resolve(), base.resolve())).as_posix()
    except ValueError:  # another drive on Windows
        return Path(path).resolve().as_uri()


def write_html_report(path: str | os.PathLike, *, title: str, sections: Sequence[ReportSection],
                      intro: Sequence[str] = (), generated_by: str = "radiomap") -> Path:
    """Write one self-contained HTML file: figures embedded as base64 data URIs (so the report shows every
    image wherever it is opened), links relative to the report's folder. Atomic write."""
    path = Path(path)
    base = path.parent
    parts = ["<!DOCTYPE html>", "<html lang='en'>", "<head>", "<meta charset='utf-8'>",
             f"<title>{html.escape(title)}</title>", f"<style>{_CSS}</style>", "</head>", "<body>",
             f"<h1>{html.escape(title)}</h1>",
             f"<p class='meta'>generated by {html.escape(generated_by)} on "
             f"{html.escape(time.strftime('%Y-%m-%d %H:%M:%S %z'))}</p>"]
    parts += [f"<p>{html.escape(p)}</p>" for p in intro]
    for k, section in enumerate(sections):
        anchor = f"s{k}"
        parts.append(f"<h2 id='{anchor}'>{html.escape(section.heading)}</h2>")
        parts += [f"<p>{html.escape(p)}</p>" for p in section.paragraphs]
        parts += [_table_html(t) for t in section.tables]
        for fig in section.figures:
            alt = html.escape(fig.caption or Path(fig.path).name, quote=True)
            rel = html.escape(_relative(fig.path, base), quote=True)
            parts.append(f"<figure><img src='{image_data_uri(fig.path)}' alt='{alt}'>"
                         f"<figcaption>{html.escape(fig.caption)} (<a href='{rel}'>{html.escape(Path(fig.path).name)}"
                         "</a>)</figcaption></figure>")
        if section.links:
            items = "".join(f"<li><a href='{html.escape(_relative(p, base), quote=True)}'>{html.escape(text)}</a></li>"
                            for text, p in section.links)
            parts.append(f"<ul>{items}</ul>")
    parts += ["</body>", "</html>", ""]
    return atomic_write_text(path, "\n".join(parts))


# --------------------------------------------------------------------------------------------------
# per-run figures: exposure estimates and trajectories
# --------------------------------------------------------------------------------------------------
def run_sections(output: str | os.PathLike, runs: Mapping[str, str | os.PathLike], *,
                 ground_truth: tuple[np.ndarray, np.ndarray] | None = None,
                 true_exposures: Mapping[float, np.ndarray] | None = None) -> tuple[list[ReportSection], dict]:
    """Report sections for what the runs' results folders hold: ``exposures.png`` (per-frame exposure
    estimates, from each run's ``exposures.txt``) and ``trajectory.png`` (camera positions from above, from each
    run's ``trajectory.txt``, with ``ground_truth`` ``(stamps, poses)`` when known). A figure is made only when
    its data exist; returns ``(sections, {"exposures"|"trajectory": path})``.

    runs:           ``{label: results folder}`` in the report's order.
    true_exposures: ``{timestamp: [k, gain_r, gain_g, gain_b]}`` (a simulated sequence's truth), drawn
                    relative to the first estimated frame.
    """
    from mapping.exposure_compensation import read_exposures
    from mapping.metrics import read_tum_trajectory
    from mapping.plots import camera_up, save_exposure_figure, save_trajectory_figure

    output = Path(output)
    exposures, trajectories = {}, {}
    for label, folder in runs.items():
        folder = Path(folder)
        if (folder / "exposures.txt").is_file():
            exposures[label] = read_exposures(folder / "exposures.txt")
        if (folder / "trajectory.txt").is_file():
            _, poses = read_tum_trajectory(folder / "trajectory.txt")
            if len(poses):
                trajectories[label] = np.asarray(poses)
    sections, files = [], {}
    if exposures:
        truth = _exposure_truth(next(iter(exposures.values())), true_exposures)
        files["exposures"] = output / "exposures.png"
        save_exposure_figure(files["exposures"], exposures, truth=truth)
        sections.append(ReportSection("Exposure estimates per frame", [
            "Each frame's exposure times white balance k per channel, estimated against the map (relative to the first "
            "frame), for every run with exposure compensation; crosses: frames whose estimate fell back."
            + (" Grey band: the simulator's true exposure." if truth is not None else "")],
            figures=[ReportFigure(files["exposures"], "Per-frame exposure estimates (R, G, B)")]))
    if trajectories:
        shown = _distinct_trajectories({k: p[:, :3, 3] for k, p in trajectories.items()})
        gt = None
        if ground_truth is not None and len(ground_truth[1]):
            gt = np.asarray(ground_truth[1])[:, :3, 3]
            if len(shown) == 1 and _same_positions(next(iter(shown.values())), gt):
                gt = None            # the runs fused at the ground truth: one line says it
                shown = {f"{next(iter(shown))} (ground-truth poses)": next(iter(shown.values()))}
        files["trajectory"] = output / "trajectory.png"
        save_trajectory_figure(files["trajectory"], shown, ground_truth=gt,
                               up=camera_up(np.concatenate(list(trajectories.values()))))
        sections.append(ReportSection("Trajectory", [
            "Camera positions seen from above (the world's vertical axis is the one closest to the cameras' mean up "
            "direction; equal scales)."
            + (" Grey band: the sequence's ground truth." if gt is not None else "")
            + " Runs that fused at the same poses share one line."],
            figures=[ReportFigure(files["trajectory"], "Camera trajectory, top view")]))
    return sections, files


def true_exposures_of(dataset) -> dict[float, np.ndarray] | None:
    """A simulated sequence's true exposures (``truth/exposures.txt``), None for other datasets or without it."""
    from radiometry.errors import RadiomapError

    read = getattr(dataset, "true_exposures", None)
    if read is None:
        return None
    try:
        return read()
    except (RadiomapError, OSError) as exc:
        log.info("no true exposures for the report: %s", exc)
        return None


def _same_positions(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and bool(np.allclose(a, b, atol=1e-6))


def _distinct_trajectories(trajectories: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``{label: positions}`` with runs of identical positions merged into one entry ("all runs" when every run
    shares one trajectory, as compare's runs do)."""
    groups: list[tuple[list[str], np.ndarray]] = []
    for label, positions in trajectories.items():
        for names, pos in groups:
            if _same_positions(pos, positions):
                names.append(label)
                break
        else:
            groups.append(([label], positions))
    if len(groups) == 1 and len(trajectories) > 1:
        return {"all runs": groups[0][1]}
    return {", ".join(names): pos for names, pos in groups}


def _exposure_truth(estimates: Mapping[str, np.ndarray], truth: Mapping[float, np.ndarray] | None
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """True ``k * gain_c`` at the estimated frames, relative to the first of them; None without truth."""
    if not truth:
        return None
    stamps = np.array(sorted(truth))
    values = np.array([truth[t] for t in stamps], dtype=np.float64)
    if values.ndim != 2 or values.shape[1] != 4:
        return None
    pick = np.abs(stamps[None, :] - np.asarray(estimates["timestamp"])[:, None]).argmin(axis=1)
    k = values[pick, :1] * values[pick, 1:]
    if not len(k) or np.any(k[0] <= 0):
        return None
    return np.asarray(estimates["index"]), k / k[0]


__all__ = ["BACKGROUND", "MeshRaycaster", "ReportFigure", "ReportSection", "ReportTable", "camera_rays",
           "GridLayout", "image_data_uri", "pick_viewpoints", "raycast_colours", "render_grid_layout",
           "render_scene_truth", "run_sections", "save_bar_chart", "save_render_grid", "scaled_intrinsics",
           "true_exposures_of", "write_html_report"]
