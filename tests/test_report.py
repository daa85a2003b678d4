"""mapping.report: CPU ray casting of vertex-coloured meshes, render grids, the self-contained HTML report."""

from __future__ import annotations

import base64
import binascii
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from mapping.report import (MeshRaycaster, ReportFigure, ReportSection, ReportTable, camera_rays, image_data_uri,
                            pick_viewpoints, raycast_colours, render_grid_layout, render_scene_truth, run_sections,
                            save_bar_chart, save_render_grid, scaled_intrinsics, write_html_report)
from radiometry.errors import OutputError

PNG = b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------------------------------
# a helper shared with test_demo / test_compare: every image of a report is present
# --------------------------------------------------------------------------------------------------
class _Refs(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.images: list[str] = []
        self.links: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a.get("src", ""))
        elif tag == "a" and a.get("href"):
            self.links.append(a["href"])


def check_report(path: Path) -> tuple[int, int]:
    """Parse an HTML report: every <img> must be an embedded base64 PNG/JPEG that decodes to an image, or a
    relative file that exists; every relative <a href> must exist. Returns (images, links) checked."""
    import cv2

    parser = _Refs()
    parser.feed(Path(path).read_text(encoding="utf-8"))
    assert parser.images, f"{path} has no images"
    for src in parser.images:
        if src.startswith("data:"):
            header, _, payload = src.partition(",")
            assert header in ("data:image/png;base64", "data:image/jpeg;base64"), header
            data = base64.b64decode(payload, validate=True)
            if header.endswith("png;base64"):
                assert data.startswith(PNG)
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            assert img is not None and img.ndim == 3 and min(img.shape[:2]) > 10, f"undecodable image in {path}"
        else:
            assert "://" not in src, f"{path} references a remote image {src}"
            assert (Path(path).parent / src).is_file(), f"{path}: image {src} is missing"
    for href in parser.links:
        if "://" in href or href.startswith("#"):
            continue
        assert (Path(path).parent / href).exists(), f"{path}: link {href} points nowhere"
    return len(parser.images), len(parser.links)


# --------------------------------------------------------------------------------------------------
# ray casting
# --------------------------------------------------------------------------------------------------
def _look_down_z(distance: float = 2.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, -distance]  # camera at z = -d looking along +z (OpenCV axes)
    return pose


def _quad(colours: np.ndarray):
    """A 2 x 2 m square at z = 0 facing the camera, corners (-1,-1), (1,-1), (1,1), (-1,1)."""
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    t = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    return v, t, np.asarray(colours, np.float32)


def test_camera_rays_follow_the_pose():
    K = np.array([[100.0, 0, 49.5], [0, 100.0, 39.5], [0, 0, 1]])
    pose = _look_down_z()
    rays = camera_rays(pose, K, 100, 80)
    assert rays.shape == (80, 100, 6) and rays.dtype == np.float32
    np.testing.assert_allclose(rays[..., :3], np.broadcast_to([0, 0, -2.0], (80, 100, 3)))
    np.testing.assert_allclose(np.linalg.norm(rays[..., 3:], axis=-1), 1.0, atol=1e-6)
    # the principal point's ray is the optical axis; pixel (99, 39.5) looks right (+x) by atan(49.5/100)
    centre = 0.5 * (rays[39, 49, 3:] + rays[40, 50, 3:])
    np.testing.assert_allclose(centre / np.linalg.norm(centre), [0, 0, 1], atol=1e-4)
    assert rays[40, 99, 3] > 0.4 and rays[0, 49, 4] < -0.3


def test_raycast_interpolates_vertex_colours_barycentrically():
    # red on the left edge, blue on the right: a horizontal ramp
    colours = [[255, 0, 0], [0, 0, 255], [0, 0, 255], [255, 0, 0]]
    v, t, c = _quad(colours)
    K = np.array([[50.0, 0, 49.5], [0, 50.0, 49.5], [0, 0, 1]])
    img = raycast_colours(v, t, c, _look_down_z(2.0), K, 100, 100, background=(7, 8, 9))
    assert img.shape == (100, 100, 3) and img.dtype == np.uint8
    # the quad spans x in [-1, 1] at 2 m: pixels 24.5 .. 74.5; a pixel at column u sees x = (u - 49.5) / 25
    for u in (30, 49, 60, 70):
        x = (u - 49.5) / 25.0
        red = 255 * (1 - x) / 2
        assert abs(int(img[50, u, 0]) - red) <= 1, (u, img[50, u])
        assert abs(int(img[50, u, 2]) - (255 - red)) <= 1
        assert img[50, u, 1] == 0
    # the same along any row (both triangles agree on the ramp)
    np.testing.assert_array_equal(img[30, 30:70], img[70, 30:70])
    # outside the quad: background
    assert tuple(img[5, 5]) == (7, 8, 9) and tuple(img[50, 95]) == (7, 8, 9)


def test_raycast_keeps_the_nearest_surface():
    v1, t1, _ = _quad(np.zeros((4, 3)))
    v2 = v1 * np.float32([0.5, 0.5, 1]) + np.float32([0, 0, -0.5])       # a smaller quad in front
    v = np.concatenate([v1, v2])
    t = np.concatenate([t1, t1 + 4])
    c = np.concatenate([np.full((4, 3), 200.0), np.full((4, 3), 20.0)])
    K = np.array([[50.0, 0, 49.5], [0, 50.0, 49.5], [0, 0, 1]])
    img = MeshRaycaster(v, t, c).render(_look_down_z(2.0), K, 100, 100)
    assert tuple(img[50, 50]) == (20, 20, 20)       # the front quad covers the centre
    assert tuple(img[50, 28]) == (200, 200, 200)    # only the back quad out there


def test_empty_mesh_renders_background_and_bad_input_is_rejected():
    K = np.array([[50.0, 0, 9.5], [0, 50.0, 9.5], [0, 0, 1]])
    img = MeshRaycaster(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros((0, 3))).render(
        np.eye(4), K, 20, 20, background=(1, 2, 3))
    assert np.all(img == np.array([1, 2, 3], np.uint8))
    v, t, c = _quad(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="colours must be"):
        MeshRaycaster(v, t, c[:3])
    with pytest.raises(ValueError, match="triangles index"):
        MeshRaycaster(v, t + 3, c)
    with pytest.raises(ValueError, match="pose must be"):
        camera_rays(np.eye(3), K, 20, 20)
    with pytest.raises(ValueError, match="K must be"):
        camera_rays(np.eye(4), np.zeros((3, 3)), 20, 20)


def test_render_scene_truth_shows_the_true_radiance():
    from mapping.simulation.scene import Face, Lighting, TexturedScene

    tex = np.zeros((4, 4, 3), np.float32)
    tex[:, :2] = [0.8, 0.2, 0.2]   # left half red, right half grey
    tex[:, 2:] = [0.5, 0.5, 0.5]
    face = Face("wall", [-1, -1, 0], [1, 0, 0], [0, 1, 0], (2.0, 2.0), tex)
    scene = TexturedScene([face], Lighting((np.pi, np.pi, np.pi), 0.0, ()))
    K = np.array([[50.0, 0, 49.5], [0, 50.0, 49.5], [0, 0, 1]])
    pose = _look_down_z(2.0)
    img = render_scene_truth(scene, pose, K, 100, 100, lambda L: np.clip(L * 255.0, 0, 255), background=(0, 0, 0))
    # ambient pi, no sky term for a face facing -z... radiance = albedo * E / pi = albedo * ambient / pi
    expected_left = scene.radiance_on_faces(np.array([0]), np.array([[0.5, 1.0]]))[0] * 255
    np.testing.assert_allclose(img[50, 35].astype(float), expected_left, atol=1.0)
    assert img[50, 35, 0] > img[50, 35, 1] and abs(int(img[50, 65, 0]) - int(img[50, 65, 1])) <= 1
    assert tuple(img[2, 2]) == (0, 0, 0)


def _turning(n: int) -> np.ndarray:
    """A camera turning on the spot about the vertical (world y here): yaw 0 .. 180 degrees."""
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    for i, a in enumerate(np.linspace(0.0, np.pi, n)):
        c, s = np.cos(a), np.sin(a)
        poses[i, :3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    return poses


def test_pick_viewpoints_spreads_distinct_views():
    poses = _turning(11)
    assert pick_viewpoints(poses, 3) == [0, 5, 10]   # the middle, then the two ends (90 degrees away)
    assert pick_viewpoints(poses, 1) == [5]
    assert pick_viewpoints(poses, 2) == [0, 5]        # ties go to the first index
    assert pick_viewpoints(poses[:2], 3) == [0, 1]
    assert pick_viewpoints(np.repeat(np.eye(4)[None], 5, axis=0), 3) == [2]   # all identical: one view
    assert pick_viewpoints(poses[:0], 3) == []
    # translation counts too: a camera sliding 4 m without turning
    slide = np.repeat(np.eye(4)[None], 9, axis=0)
    slide[:, 0, 3] = np.linspace(0, 4, 9)
    assert pick_viewpoints(slide, 3) == [0, 4, 8]
    with pytest.raises(ValueError, match="poses must be"):
        pick_viewpoints(np.eye(4), 2)
    with pytest.raises(ValueError, match="n must be"):
        pick_viewpoints(poses, 0)


def test_scaled_intrinsics_keeps_the_field_of_view():
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    K2, w, h = scaled_intrinsics(K, 640, 480, 160)
    assert (w, h) == (160, 120)
    np.testing.assert_allclose(K2, [[131.25, 0, 79.5], [0, 131.25, 59.5], [0, 0, 1]])


# --------------------------------------------------------------------------------------------------
# figures and HTML
# --------------------------------------------------------------------------------------------------
def test_render_grid_has_one_tile_per_method_and_view(tmp_path):
    import cv2

    tiles = {f"m{j}": [np.full((60, 80, 3), 40 * j + 20 * r, np.uint8) for r in range(2)] for j in range(3)}
    path = save_render_grid(tmp_path / "grid.png", tiles, row_labels=["view 1", "view 2"], title="t")
    img = cv2.imread(str(path))
    assert img is not None
    # a row per method, a column per view; small renders enlarged (here 4x, the most) towards a 900 px grid
    layout = render_grid_layout(3, 2, 80, 60, title=True)
    assert layout.scale == 4 and img.shape[:2] == (layout.height, layout.width)
    assert 800 <= layout.width <= 1300
    for j in range(3):
        for r in range(2):
            x, y, w, h = layout.tile(j, r)
            assert (w, h) == (320, 240)
            np.testing.assert_array_equal(img[y:y + h, x:x + w], 40 * j + 20 * r)   # the tile, nothing over it
    assert img[:, :layout.label_width].min() < 128      # the method labels are drawn on the left
    # renders of a full-size sequence stay at their size: 3 views of 320 px already fill the width
    assert render_grid_layout(5, 3, 320, 240).scale == 1
    with pytest.raises(ValueError, match="same number"):
        save_render_grid(tmp_path / "bad.png", {"a": [tiles["m0"][0]], "b": tiles["m1"]})
    with pytest.raises(ValueError, match="at least one"):
        save_render_grid(tmp_path / "bad.png", {})


def test_html_report_embeds_every_figure_and_escapes_text(tmp_path):
    import cv2

    img = np.zeros((40, 50, 3), np.uint8)
    img[:, :25] = 255
    cv2.imwrite(str(tmp_path / "a.png"), img)
    save_bar_chart(tmp_path / "bars.png", {"none": 3.0, "lut": 1.5}, ylabel="levels")
    (tmp_path / "mesh.ply").write_text("ply\n")
    section = ReportSection("Results <b>", ["1 < 2 & 3 > 2"],
                            tables=[ReportTable("t", [{"method": "<script>", "L1 mean": 1.23456,
                                                       "x": float("nan")}])],
                            figures=[ReportFigure(tmp_path / "a.png", "first"),
                                     ReportFigure(tmp_path / "bars.png", "bars")],
                            links=[("mesh", str(tmp_path / "mesh.ply"))])
    path = write_html_report(tmp_path / "sub" / ".." / "report.html", title="T & T", sections=[section])
    text = Path(path).read_text(encoding="utf-8")
    assert "<script>" not in text and "&lt;script&gt;" in text and "1.23" in text
    assert "T &amp; T" in text and "1 &lt; 2 &amp; 3 &gt; 2" in text
    images, links = check_report(path)
    assert images == 2 and links == 3   # two figure links and the mesh
    # the embedded PNG is exactly the file
    src = text.split("src='")[1].split("'")[0]
    assert base64.b64decode(src.split(",", 1)[1]) == (tmp_path / "a.png").read_bytes()
    # a moved report still shows its images (they are embedded)
    moved = tmp_path / "elsewhere" / "copy.html"
    moved.parent.mkdir()
    moved.write_text(text, encoding="utf-8")
    parser = _Refs()
    parser.feed(moved.read_text(encoding="utf-8"))
    assert all(s.startswith("data:image/png;base64,") for s in parser.images)


def test_image_data_uri_rejects_missing_and_non_images(tmp_path):
    with pytest.raises(OutputError, match="cannot embed"):
        image_data_uri(tmp_path / "missing.png")
    (tmp_path / "x.png").write_text("not an image")
    with pytest.raises(OutputError, match="not a PNG or JPEG"):
        image_data_uri(tmp_path / "x.png")


def test_check_report_catches_a_missing_image(tmp_path):
    (tmp_path / "r.html").write_text("<html><body><img src='nope.png'></body></html>")
    with pytest.raises(AssertionError, match="missing"):
        check_report(tmp_path / "r.html")
    bad = base64.b64encode(b"garbage").decode()
    (tmp_path / "r2.html").write_text(f"<img src='data:image/png;base64,{bad}'>")
    with pytest.raises((AssertionError, binascii.Error)):
        check_report(tmp_path / "r2.html")


def test_table_columns_of_text_are_left_aligned_and_numbers_right(tmp_path):
    section = ReportSection("r", tables=[ReportTable("t", [
        {"method": "none", "description": "no correction", "L1 mean": 25.9, "ATE cm": "-", "unit": "levels"},
        {"method": "lut", "description": "LUT vignetting", "L1 mean": 11.2, "ATE cm": 1.5, "unit": "levels"}])])
    text = Path(write_html_report(tmp_path / "r.html", title="t", sections=[section])).read_text(encoding="utf-8")
    header = text.split("<tr>")[1]
    assert "<th>method</th><th>description</th><th class='num'>L1 mean</th><th class='num'>ATE cm</th>" \
           "<th>unit</th>" in header
    assert "<td>LUT vignetting</td><td class='num'>11.20</td><td class='num'>1.50</td><td>levels</td>" in text
    css = text.split("<style>")[1].split("</style>")[0]
    assert "text-align: left" in css and "td.num { text-align: right; }" in css.replace("th.num, ", "")
    assert "figure img { width: 100%;" in css           # figures span the page


def test_report_figures_are_drawn_for_the_full_width(tmp_path):
    import cv2

    from mapping.histogram import DisagreementHistogram
    from mapping.plots import save_histogram_figure

    save_bar_chart(tmp_path / "bars.png", {"none": 11.56, "response": 11.16, "poly": 3.03, "lut": 2.03},
                   ylabel="levels")
    bars = cv2.imread(str(tmp_path / "bars.png"))
    assert bars.shape[:2] == (400, 1200)
    hists = {name: DisagreementHistogram(label=name) for name in ("a", "b")}
    for k, h in enumerate(hists.values()):
        h.add_distances(np.arange(50, dtype=np.float64) % (10 + k))
    save_histogram_figure(tmp_path / "h.png", hists, title="t")
    assert cv2.imread(str(tmp_path / "h.png")).shape[:2] == (520, 1200)


def test_bar_labels_stay_inside_the_frame(monkeypatch):
    import mapping.report as report

    captured = {}

    def keep(fig, path, **kwargs):
        captured["fig"] = fig
        return path

    monkeypatch.setattr(report, "save_figure", keep)
    save_bar_chart("unused.png", {"none": 11.56, "lut": 2.03}, ylabel="levels")
    fig = captured["fig"]
    ax = fig.axes[0]
    fig.canvas.draw()
    frame = ax.get_window_extent()
    labels = [t for t in ax.texts if t.get_text() in ("11.56", "2.03")]
    assert len(labels) == 2
    for t in labels:   # clear of the frame line (the old chart left 0.7 px above "11.56": the line crossed it)
        box = t.get_window_extent()
        assert box.y1 < frame.y1 - 5 and box.y0 > frame.y0, t.get_text()


def test_histogram_curves_differ_in_line_style_and_markers():
    from matplotlib.figure import Figure

    from mapping.plots import plot_histograms

    counts = np.zeros(256)
    counts[5:15] = 1.0
    ax = Figure().subplots()
    plot_histograms(ax, {f"m{i}": counts for i in range(4)})   # four identical curves
    curves = [line for line in ax.get_lines() if line.get_label().startswith("m")]
    assert len(curves) == 4
    assert len({line.get_linestyle() for line in curves}) == 4
    assert len({line.get_marker() for line in curves}) == 4
    assert len({line.get_color() for line in curves}) == 4


def _run_folder(folder: Path, *, exposures: bool, offset: float = 0.0, n: int = 12) -> Path:
    from mapping.metrics import write_tum_trajectory

    folder.mkdir(parents=True)
    stamps = 100.0 + np.arange(n) / 30.0
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 0, 3] = np.linspace(0.0, 1.0, n) + offset
    poses[:, 1, 3] = np.sin(np.linspace(0.0, 3.0, n))
    poses[:, :3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]     # camera y (down in the image) along world -z
    write_tum_trajectory(folder / "trajectory.txt", stamps, poses)
    if exposures:
        lines = ["# index timestamp k_r k_g k_b correspondences source"]
        lines += [f"{i} {t:.6f} {1 + 0.01 * i:.4f} {1 + 0.02 * i:.4f} 1.0 {0 if i == 0 else 500} "
                  f"{'reference' if i == 0 else 'fallback' if i == 5 else 'map'}" for i, t in enumerate(stamps)]
        (folder / "exposures.txt").write_text("\n".join(lines) + "\n")
    return folder


def test_run_sections_plot_exposures_and_trajectories_when_they_exist(tmp_path):
    import cv2

    a = _run_folder(tmp_path / "a", exposures=False)
    b = _run_folder(tmp_path / "b", exposures=True, offset=0.1)
    n = 12
    stamps = 100.0 + np.arange(n) / 30.0
    gt = np.repeat(np.eye(4)[None], n, axis=0)
    truth = {float(t): np.array([1.0 + 0.01 * i, 1.0, 1.0, 1.0]) for i, t in enumerate(stamps)}
    sections, files = run_sections(tmp_path, {"raw": a, "lut+ec": b}, ground_truth=(stamps, gt),
                                   true_exposures=truth)
    assert [s.heading for s in sections] == ["Exposure estimates per frame", "Trajectory"]
    assert set(files) == {"exposures", "trajectory"}
    for path in files.values():
        img = cv2.imread(str(path))
        assert img is not None and img.shape[1] == 1200 and 400 <= img.shape[0] <= 600
    assert "true exposure" in sections[0].paragraphs[0] and "ground truth" in sections[1].paragraphs[0]
    # no exposure estimates, no ground truth, one shared trajectory: one figure, one line
    only = tmp_path / "only"
    only.mkdir()
    sections, files = run_sections(only, {"raw": a, "again": _run_folder(tmp_path / "c", exposures=False)})
    assert [s.heading for s in sections] == ["Trajectory"] and not (only / "exposures.png").exists()
    # nothing to plot: no sections, no files
    empty = tmp_path / "empty"
    empty.mkdir()
    assert run_sections(empty, {"x": empty}) == ([], {})
    assert list(empty.iterdir()) == []


def test_top_view_drops_the_vertical():
    from mapping.plots import camera_up, top_view_axes

    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    poses[:, :3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]     # camera y along world -z: z is up
    positions = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 2.0], [0.02, 0.01, 1.0]])   # moving mostly in z
    assert top_view_axes(positions, camera_up(poses)) == (0, 1)
    assert top_view_axes(positions) == (0, 2)                # without poses: the axis of least spread (y)
