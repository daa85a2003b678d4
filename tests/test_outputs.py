"""Lean outputs (issue 32): one mesh by default, others with ``--formats`` (checked before anything is written), the
list of what a command wrote; which file suits which tool (docs/outputs.md, its claims checked by loading the files);
``-vv`` shows radiomap's logs only; the exposures legend fits; the sample cache in the user's cache folder."""

from __future__ import annotations

import logging
import os
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from mapping.cli import cli
from mapping.export import write_mesh
from radiometry.response import srgb_to_linear

VERTICES = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
TRIANGLES = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
DISPLAY = np.array([[200, 128, 30], [64, 64, 64], [255, 0, 128], [10, 100, 250]], np.float32)   # display levels


def _mesh(folder, formats=None):
    kwargs = {} if formats is None else {"formats": formats}
    return write_mesh(folder, VERTICES, TRIANGLES, DISPLAY, lambda c: c, **kwargs)


def test_one_ply_by_default_and_the_others_on_request(tmp_path):
    (tmp_path / "a").mkdir()
    assert set(_mesh(tmp_path / "a")) == {"mesh_ply"}
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["mesh.ply"]
    (tmp_path / "b").mkdir()
    files = _mesh(tmp_path / "b", ("ply", "glb", "obj", "npz"))
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["mesh.glb", "mesh.obj", "mesh.ply",
                                                                  "mesh_colours.npz"]
    assert set(files) == {"mesh_ply", "mesh_glb", "mesh_obj", "mesh_colours"}
    with pytest.raises(ValueError, match=r"--formats 'stl': unknown mesh format 'stl'; choose from ply, glb, obj, npz"):
        _mesh(tmp_path / "b", ("stl",))


@pytest.mark.parametrize("command", ["reconstruct", "compare", "demo", "batch"])
def test_an_unknown_format_is_one_line_before_anything_is_written(command, tmp_path):
    seq = tmp_path / "seq"
    seq.mkdir()
    out = tmp_path / "out"
    response = tmp_path / "crf.npz"
    response.write_bytes(b"not read: the options are checked first")
    args = {"reconstruct": ["reconstruct", str(seq), "-o", str(out), "--formats", "ply,stl"],
            "compare": ["compare", str(seq), "-r", str(response), "-o", str(out), "--formats", "ply,stl"],
            "demo": ["demo", "-o", str(out), "--formats", "ply,stl"],
            "batch": ["batch", "reconstruct", str(tmp_path / "list.txt"), "-o", str(out), "--", "--formats",
                      "ply,stl"]}[command]
    (tmp_path / "list.txt").write_text(f"{seq}\n")
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 1, res.output
    lines = res.output.strip().splitlines()
    assert lines == ["radiomap: error: --formats 'ply,stl': unknown mesh format 'stl'; choose from ply, glb, obj, "
                     "npz, comma-separated (e.g. --formats ply,glb)"], res.output
    assert not out.exists()


# ------------------------------------------------------------------ docs/outputs.md: which file for which tool
def test_open3d_reads_the_ply_as_display_colours_and_the_glb_linear(tmp_path):
    """The table's Open3D row: the PLY (and OBJ) give the display colours (sRGB-encoded) / 255; the GLB gives glTF's
    linear COLOR_0 as it is, i.e. a darker mesh when shown as display colours."""
    from mapping._open3d import o3d

    _mesh(tmp_path, ("ply", "glb", "obj"))
    for name in ("mesh.ply", "mesh.obj"):
        got = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / name)).vertex_colors)
        np.testing.assert_allclose(got, DISPLAY / 255, atol=1e-6)
    got = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "mesh.glb")).vertex_colors)
    np.testing.assert_allclose(got, srgb_to_linear(DISPLAY / 255), atol=1e-6)
    assert got[0, 0] < DISPLAY[0, 0] / 255 - 0.15     # 200 -> 0.578 instead of 0.784: darker


def test_trimesh_keeps_the_glb_colours_in_vertex_attributes_and_drops_them_on_export(tmp_path):
    import trimesh

    _mesh(tmp_path, ("ply", "glb"))
    ply = trimesh.load(tmp_path / "mesh.ply", process=False)
    np.testing.assert_array_equal(np.asarray(ply.visual.vertex_colors)[:, :3], DISPLAY.astype(np.uint8))
    scene = trimesh.load(tmp_path / "mesh.glb", process=False)
    (mesh,) = scene.geometry.values()
    assert not hasattr(mesh.visual, "vertex_colors")      # TextureVisuals: no vertex_colors
    np.testing.assert_allclose(mesh.visual.vertex_attributes["color"][:, :3], srgb_to_linear(DISPLAY / 255),
                               atol=1e-6)
    scene.export(tmp_path / "again.glb")
    (again,) = trimesh.load(tmp_path / "again.glb", process=False).geometry.values()
    assert "color" not in again.visual.vertex_attributes     # lost on re-export


# ------------------------------------------------------------------ one small run: formats, the list, -vv
@pytest.fixture(scope="module")
def verbose_run(tmp_path_factory):
    """``radiomap -vv reconstruct`` of 5 frames of the sample room, as a user starts it (a new process)."""
    from mapping.simulation import sample_sequence

    room = sample_sequence("room")
    out = tmp_path_factory.mktemp("outputs") / "run"
    res = subprocess.run([sys.executable, "-m", "mapping.cli", "-vv", "reconstruct", str(room), "-o", str(out),
                          "--poses", "gt", "--frames", "0:5", "--voxel-size", "0.05", "--depth-max", "4",
                          "--no-progress"], capture_output=True, text=True, env=dict(os.environ, MPLBACKEND="Agg"))
    assert res.returncode == 0, res.stderr[-2000:]
    return out, res


def test_reconstruct_writes_one_mesh_and_lists_what_it_wrote(verbose_run):
    out, res = verbose_run
    assert (out / "mesh.ply").is_file()
    assert not (out / "mesh.glb").exists() and not (out / "mesh_colours.npz").exists()
    listed = res.stderr[res.stderr.index(f"wrote {out}: "):].splitlines()
    assert any(line.split()[0] == "mesh.ply" and line.split()[-1] in ("kB", "MB") for line in listed[1:])
    assert "settings: " in res.stdout and "formats ply (reconstruct's default)" in res.stdout


def test_vv_shows_radiomap_logs_only(verbose_run):
    _, res = verbose_run
    logged = [line for line in res.stderr.splitlines() if line.split(" ", 1)[0] in ("DEBUG", "INFO")]
    names = {line.split(" ", 2)[1].rstrip(":").split(".")[0] for line in logged}
    assert "mapping" in names                  # -vv shows radiomap's DEBUG lines (e.g. "frame K of N: fused")
    assert names <= {"mapping", "radiometry", "radiomap"}, names - {"mapping", "radiometry", "radiomap"}
    assert not [line for line in res.stderr.splitlines() if "font_manager" in line or "findfont" in line]


def test_third_party_loggers_stay_at_warning():
    from mapping.cli import configure_logging

    try:
        configure_logging(2)
        assert logging.getLogger("mapping.pipeline").isEnabledFor(logging.DEBUG)
        for name in ("matplotlib.font_manager", "numba", "PIL", "ray", "urllib3"):
            assert not logging.getLogger(name).isEnabledFor(logging.INFO), name
    finally:
        configure_logging(0)
    assert logging.getLogger("mapping").level == logging.NOTSET   # without -v: as the root logger says


# ------------------------------------------------------------------ the report's exposures legend
def test_exposure_legend_fits_inside_the_figure(monkeypatch):
    import mapping.figure_files
    from mapping.plots import save_exposure_figure

    captured = {}
    monkeypatch.setattr(mapping.figure_files, "save_figure", lambda fig, path, **kw: captured.setdefault("fig", fig))
    n = 30
    run = {"index": np.arange(n), "k": np.ones((n, 3)), "source": np.array(["map"] * n)}
    names = ["no correction", "polynomial vignetting + exposure compensation", "LUT vignetting + exposure "
             "compensation", "self-calibrated vignetting + exposure compensation", "no correction + exposure "
             "compensation"]       # the demo's five curves and the truth: 4 columns of these ran off both sides
    save_exposure_figure("unused.png", {k: run for k in names}, truth=(np.arange(n), np.ones((n, 3))), title="t")
    fig = captured["fig"]
    fig.canvas.draw()
    (legend,) = fig.legends
    box, frame = legend.get_window_extent(), fig.bbox
    assert frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1, (box, frame)
    assert [t.get_text() for t in legend.get_texts()] == ["truth", *names]
    for ax in fig.axes:            # below the axes and their labels, not over them
        assert box.y1 <= ax.get_tightbbox().y0 + 1


# ------------------------------------------------------------------ the cache
def test_the_cache_is_in_the_users_cache_folder(monkeypatch, tmp_path):
    from mapping.simulation.samples import cache_dir, samples_root

    monkeypatch.delenv("RADIOMAP_SAMPLES_DIR", raising=False)
    monkeypatch.setenv("RADIOMAP_CACHE_DIR", str(tmp_path / "c"))
    assert cache_dir() == tmp_path / "c" and samples_root() == tmp_path / "c" / "samples"
    monkeypatch.delenv("RADIOMAP_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "radiomap"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/path")     # the XDG specification: relative paths are ignored
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_dir() == tmp_path / "home" / ".cache" / "radiomap"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert cache_dir() == tmp_path / "home" / ".cache" / "radiomap"


def test_the_tests_cache_is_not_in_the_home_folder():
    from mapping.simulation.samples import samples_root

    assert not samples_root().resolve().is_relative_to(os.path.expanduser("~"))


def test_the_first_sample_written_says_where_once(monkeypatch, tmp_path, caplog):
    from mapping.simulation import sample_sequence

    monkeypatch.delenv("RADIOMAP_SAMPLES_DIR", raising=False)
    monkeypatch.setenv("RADIOMAP_CACHE_DIR", str(tmp_path / "cache"))
    with caplog.at_level(logging.WARNING, logger="mapping.simulation.samples"):
        first = sample_sequence("brackets")
        said = [r.getMessage() for r in caplog.records if r.name == "mapping.simulation.samples"]
        assert first == tmp_path / "cache" / "samples" / "brackets" and (first / "times.txt").is_file()
        assert len(said) == 1 and str(tmp_path / "cache" / "samples") in said[0]
        caplog.clear()
        assert sample_sequence("brackets") == first
        assert not [r for r in caplog.records if r.name == "mapping.simulation.samples"]
