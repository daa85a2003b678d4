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
from radiometry.fileio import atomic_path, atomic_write_text

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
def _save_figure(fig, path: str | os.PathLike, *, dpi: int = 100) -> Path:
    """PNG, or JPEG (quality 90) for a ``.jpg``/``.jpeg`` path; atomic."""
    path = Path(path)
    fmt = (path.suffix.lstrip(".") or "png").lower()
    kwargs = {"pil_kwargs": {"quality": 90}} if fmt in ("jpg", "jpeg") else {}
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="jpeg" if fmt == "jpg" else fmt, **kwargs)
    return path


def save_render_grid(path: str | os.PathLike, columns: Mapping[str, Sequence[np.ndarray]], *,
                     row_labels: Sequence[str] | None = None, title: str | None = None, dpi: int = 100) -> Path:
    """Images side by side: one column per entry of ``columns`` (``{label: [image per view]}``), one row per
    view, at their native pixel size; written atomically (PNG, or JPEG for a ``.jpg`` path)."""
    from matplotlib.figure import Figure

    if not columns:
        raise ValueError("columns must hold at least one method's renders")
    rows = {len(v) for v in columns.values()}
    if len(rows) != 1 or 0 in rows:
        raise ValueError(f"every column must have the same number (> 0) of views, got {sorted(rows)}")
    n_rows, n_cols = rows.pop(), len(columns)
    first = next(iter(columns.values()))[0]
    h, w = first.shape[:2]
    label_h, side = 0.32, (0.3 if row_labels else 0.0)
    fig_w = n_cols * w / dpi + side
    fig_h = n_rows * h / dpi + label_h * (1.0 if not title else 1.9)
    fig = Figure(figsize=(fig_w, fig_h), dpi=dpi)
    top = 1.0 - (label_h * (1.9 if title else 1.0)) / fig_h
    left = side / fig_w
    for c, (label, images) in enumerate(columns.items()):
        for r, img in enumerate(images):
            ax = fig.add_axes((left + c * (1 - left) / n_cols, top - (r + 1) * top / n_rows,
                               (1 - left) / n_cols, top / n_rows))
            ax.imshow(np.asarray(img), interpolation="nearest")
            ax.set_axis_off()
            if r == 0:
                ax.set_title(str(label), fontsize=9, pad=3)
            if c == 0 and row_labels:
                fig.text(left * 0.5, top - (r + 0.5) * top / n_rows, str(row_labels[r]), rotation=90,
                         ha="center", va="center", fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10, y=1.0 - 0.35 * label_h / fig_h, va="top")
    return _save_figure(fig, path, dpi=dpi)


def save_bar_chart(path: str | os.PathLike, values: Mapping[str, float], *, ylabel: str, title: str | None = None
                   ) -> Path:
    """A small bar chart (one bar per method)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(max(4.0, 1.1 * len(values) + 1.5), 3.2))
    ax = fig.subplots()
    names = list(values)
    heights = [float(values[n]) for n in names]
    bars = ax.bar(range(len(names)), heights, color="#4c72b0")
    for b, v in zip(bars, heights):
        if math.isfinite(v):
            ax.text(b.get_x() + b.get_width() / 2, v, f"{v:.2f}", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(range(len(names)), names, rotation=15, ha="right", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.grid(True, axis="y", alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _save_figure(fig, path, dpi=110)


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
body { font-family: system-ui, -apple-system, 'Segoe UI', sans-serif; margin: 2em auto; max-width: 1200px;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; } h2 { font-size: 1.25em; margin-top: 1.8em;
       border-bottom: 1px solid #ddd; padding-bottom: 0.2em; }
.meta { color: #666; font-size: 0.9em; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.7em; text-align: right; }
th { background: #f3f3f6; } td:first-child, th:first-child { text-align: left; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
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


def _table_html(table: ReportTable) -> str:
    if not table.rows:
        return f"<p><em>{html.escape(table.title)}: no rows</em></p>"
    columns = table.columns or list(table.rows[0].keys())
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in columns)
    body = "\n".join("<tr>" + "".join(f"<td>{_cell(r.get(c))}</td>" for c in columns) + "</tr>" for r in table.rows)
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


__all__ = ["BACKGROUND", "MeshRaycaster", "ReportFigure", "ReportSection", "ReportTable", "camera_rays",
           "image_data_uri", "pick_viewpoints", "raycast_colours", "render_scene_truth", "save_bar_chart",
           "save_render_grid", "scaled_intrinsics", "write_html_report"]
