"""The Python API: ``mapping.reconstruct_sequence``, ``radiometry.calibrate_*`` / ``correct``, light imports,
open3d imported before radiomap, and the docs' worked example (docs/examples/from_python.py) run as written."""

from __future__ import annotations

import inspect
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

import mapping
import radiometry
from radiometry.errors import DatasetError, RadiomapError

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "docs" / "examples" / "from_python.py"
BRACKETS = ROOT / "data_samples" / "brackets"
FRAMES = slice(0, 8)


@pytest.fixture(scope="module")
def room():
    from mapping.simulation import sample_sequence

    return sample_sequence("room")


@pytest.fixture(scope="module")
def truth(room):
    from mapping.datasets import open_dataset

    ds = open_dataset(room)
    return {"response": ds.truth_path("response.npz"), "vignetting": ds.truth_path("vignetting.npy")}


def _python(code: str, *, env: dict | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env=env, cwd=cwd)


def _env_without_libusb() -> dict:
    """This environment with no LD_LIBRARY_PATH entry that holds a libusb (what a fresh notebook kernel has)."""
    env = dict(os.environ)
    paths = [p for p in env.get("LD_LIBRARY_PATH", "").split(os.pathsep)
             if p and not list(Path(p).glob("libusb-1.0*"))]
    env["LD_LIBRARY_PATH"] = os.pathsep.join(paths)
    return env


# ------------------------------------------------------------------------------------------------ imports
def test_imports_are_light():
    proc = _python("import sys, mapping, radiometry\n"
                   "heavy = ('open3d', 'trimesh', 'scipy', 'cv2', 'matplotlib', 'numba', 'tqdm', 'mapping.pipeline')\n"
                   "print([m for m in heavy if m in sys.modules])\n"
                   "print(callable(mapping.reconstruct_sequence), callable(radiometry.calibrate_response))")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split("\n")[:2] == ["[]", "True True"]


@pytest.mark.slow
def test_open3d_after_mapping_and_the_notebook_fix():
    """A notebook that imports open3d first: without a system libusb that import fails (ImportError naming
    libusb-1.0.so.0); the one-line fix, ``import mapping``, then makes ``import open3d`` work in the same
    process. Importing mapping first works from the start."""
    env = _env_without_libusb()
    proc = _python("try:\n    import open3d\nexcept ImportError as exc:\n    print('first import failed:', exc)\n"
                   "else:\n    print('first import worked')\n"
                   "import mapping\nimport open3d\nprint('open3d', open3d.__version__)", env=env)
    assert proc.returncode == 0, proc.stderr
    first, last = proc.stdout.splitlines()[0], proc.stdout.splitlines()[-1]
    assert first == "first import worked" or ("first import failed" in first and "libusb" in first)
    assert last.startswith("open3d ")
    proc = _python("import mapping, open3d; print(open3d.geometry.TriangleMesh.create_box().has_triangles())", env=env)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "True"


# ------------------------------------------------------------------------------------------------ radiometry
@pytest.mark.slow
def test_calibrate_response_folder_and_arrays_match_the_command_path():
    from radiometry.response.fit import fit_response, load_brackets

    # quality="fast": the full figure (a refit per exposure and two half fits, 50 of this call's 56 s of CPU) is the
    # command's default, tested through `radiomap response` (tests/test_cli_response.py, test_calibration_pipelines.py)
    response = radiometry.calibrate_response(BRACKETS, progress=False, quality="fast")
    assert response.meta["quality"]["grade"] in ("good", "doubtful", "broken")
    images, times, _ = load_brackets(BRACKETS, progress=False)
    direct = fit_response(images, times, method="loglog")  # what auto picks for the sample's 4x steps
    np.testing.assert_array_equal(response.inverse_table, direct.inverse_table)
    assert 0 < response.meta["prediction_rms_levels"] < 10
    from_arrays = radiometry.calibrate_response(images, times, method="robertson")
    assert from_arrays.meta["method"] == "robertson"
    with pytest.raises(ValueError, match="times must be the images' exposure times"):
        radiometry.calibrate_response(images)
    with pytest.raises(DatasetError, match="no such folder"):
        radiometry.calibrate_response(BRACKETS / "missing")


def test_correct_and_calibrate_vignetting(tmp_path, truth):
    from radiometry.correction import Corrector
    from radiometry.images import read_rgb
    from radiometry.vignetting import LUTVignetting

    response = radiometry.load_response(truth["response"])
    lut = LUTVignetting(np.load(truth["vignetting"]))
    frame = sorted((Path(truth["response"]).parents[1] / "rgb").glob("*.png"))[0]
    expected = Corrector(response, lut).correct(read_rgb(frame), scale=0.9)
    np.testing.assert_array_equal(radiometry.correct(frame, truth["response"], lut, scale=0.9), expected)
    irr = radiometry.correct(read_rgb(frame), response, lut.lut, irradiance=True)
    assert irr.dtype == np.float32 and irr.shape == expected.shape
    # a tiny white-paper sweep of the same simulated camera family
    from mapping.simulation import simulate_paper

    sweep = simulate_paper(tmp_path / "paper", seed=3, n_frames=40, width=96, height=72, progress=False)
    sweep_response = radiometry.load_response(sweep / "truth" / "response.npz")
    model = radiometry.calibrate_vignetting(sweep / "rgb", sweep_response, model="poly", progress=False)
    true_v = np.load(sweep / "truth" / "vignetting.npy")
    assert model.evaluate(72, 96).shape == true_v.shape
    assert np.median(np.abs(model.evaluate(72, 96) - true_v)) < 0.05
    with pytest.raises(ValueError, match="smooth_sigma applies to model='lut' only"):
        radiometry.calibrate_vignetting(sweep / "rgb", sweep_response, model="poly", smooth_sigma=2.0)


# ------------------------------------------------------------------------------------------------ mapping
def test_keywords_are_the_commands_long_options():
    """Every option of ``radiomap reconstruct`` is a keyword of reconstruct_sequence under its long name with
    underscores (``--no-x`` flags as ``x``)."""
    from mapping.api import option_names
    from mapping.cli.reconstruct import command

    accepted = set(inspect.signature(mapping.reconstruct_sequence).parameters) | set(option_names())
    names = set()
    for param in command.params:
        longs = [o for o in param.opts if o.startswith("--")]
        if not longs or getattr(param, "hidden", False):   # SEQUENCE (the path); old spellings kept as aliases
            continue
        name = longs[0][2:].replace("-", "_")
        names.add(name[3:] if name.startswith("no_") else name)
    names -= {"config", "help"}   # replaying a config.json is the command's business
    assert names <= accepted, sorted(names - accepted)


def test_bad_arguments(room, tmp_path):
    with pytest.raises(TypeError, match="unknown options voxelsize; valid: .*voxel_size"):
        mapping.reconstruct_sequence(room, voxelsize=0.02)
    with pytest.raises(DatasetError, match="no such sequence folder"):
        mapping.reconstruct_sequence(tmp_path / "nothing")
    with pytest.raises(ValueError, match="needs the camera response"):
        mapping.reconstruct_sequence(room, vignetting=np.ones((240, 320, 3), np.float32), frames=FRAMES)
    with pytest.raises(TypeError, match="response must be a CameraResponse"):
        mapping.reconstruct_sequence(room, response=2.2)
    assert list(tmp_path.iterdir()) == []


def _listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.mark.slow
def test_reconstruct_without_output_leaves_nothing_and_matches_the_results_folder(room, truth, tmp_path, monkeypatch):
    """output=None: no file anywhere (the mesh goes through a temporary folder, removed); the mesh, as trimesh
    and Open3D objects, holds the colours the results folder's mesh.ply holds; models as objects or files
    give the same run."""
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    monkeypatch.chdir(scratch)
    before = _listing(room)
    response = radiometry.load_response(truth["response"])
    vignetting = np.load(truth["vignetting"])
    memory = mapping.reconstruct_sequence(room, response=response, vignetting=vignetting, poses="gt", frames=FRAMES,
                                          depth_max=5.0, progress=False)
    assert memory.output is None and memory.files == {} and memory.exposure_compensation
    assert memory.fused == 8 and memory.status == "complete"
    mesh = memory.mesh_trimesh()
    o3d_mesh = memory.mesh_open3d()
    assert _listing(scratch) == [] and _listing(room) == before

    out = tmp_path / "run"
    saved = mapping.reconstruct_sequence(str(room), out, response=truth["response"], vignetting=truth["vignetting"],
                                         poses="gt", frames=FRAMES, depth_max=5.0, progress=False)
    assert saved.output == out and (out / "mesh.ply").is_file() and (out / "exposures.txt").is_file()
    np.testing.assert_array_equal(saved.histogram.counts, memory.histogram.counts)
    import trimesh

    ply = trimesh.load(out / "mesh.ply", process=False)
    assert len(mesh.vertices) == len(ply.vertices) > 1000 and len(mesh.faces) == len(ply.faces)
    # the same surface and colours; Open3D's voxel hash map orders the vertices differently in each run
    np.testing.assert_array_equal(_sorted_rows(mesh.vertices, mesh.visual.vertex_colors),
                                  _sorted_rows(ply.vertices, ply.visual.vertex_colors))
    from_folder = saved.mesh_trimesh()
    np.testing.assert_array_equal(from_folder.vertices, ply.vertices)
    np.testing.assert_array_equal(from_folder.faces, ply.faces)
    np.testing.assert_array_equal(from_folder.visual.vertex_colors, ply.visual.vertex_colors)
    colours = np.asarray(o3d_mesh.vertex_colors)
    np.testing.assert_allclose(colours * 255.0, mesh.visual.vertex_colors[:, :3], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(o3d_mesh.triangles), mesh.faces)
    assert o3d_mesh.has_vertex_normals()
    config = json.loads((out / "config.json").read_text())
    assert config["command"] == "mapping.reconstruct_sequence"
    assert config["parameters"]["frames"] == "0:8" and config["parameters"]["depth_max"] == 5.0
    assert config["parameters"]["response"] == str(truth["response"])


def _sorted_rows(vertices: np.ndarray, colours: np.ndarray) -> np.ndarray:
    rows = np.concatenate([np.round(np.asarray(vertices, np.float64), 5), np.asarray(colours, np.float64)], axis=1)
    return rows[np.lexsort(rows.T[::-1])]


@pytest.mark.slow
def test_raw_run_and_surfels_without_a_mesh(room):
    raw = mapping.reconstruct_sequence(room, poses="gt", frames=slice(0, 3), depth_max=5.0, progress=False)
    assert not raw.exposure_compensation and raw.colour_model.describe()["name"] == "none"
    assert raw.mesh_trimesh().visual.vertex_colors.dtype == np.uint8
    surfels = mapping.reconstruct_sequence(room, poses="gt", frames=slice(0, 3), depth_max=5.0, backend="surfel",
                                           progress=False)
    with pytest.raises(RadiomapError, match="surfel_mesh=True"):
        surfels.mesh_trimesh()


@pytest.mark.slow
def test_holdout_and_colour_map_through_the_library(room, truth, tmp_path):
    """holdout_every and colour_map reach the run as the command's options do: the withheld frames are judged
    (metrics.json, holdout.csv) and never fused; the colour-map stage runs after fusion and says which mesh it
    kept; an impossible holdout_every stops before anything is written."""
    out = tmp_path / "run"
    run = mapping.reconstruct_sequence(room, out, response=truth["response"], vignetting=truth["vignetting"],
                                       poses="gt", frames=FRAMES, depth_max=5.0, progress=False, holdout_every=4,
                                       colour_map="rigid")
    assert run.fused == 6 and run.holdout is not None and len(run.holdout.frames) == 2
    assert 10 < run.holdout.psnr < 80 and run.holdout.l1 > 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["holdout"]["frames_held_out"] == 2
    assert (out / "holdout.csv").read_text().count("\n") == 3
    assert run.colour_map is not None and run.colour_map.kept in ("optimised", "plain") and run.colour_map.reason
    assert (out / "colour_map.json").is_file()
    with pytest.raises(RadiomapError, match="holdout"):
        mapping.reconstruct_sequence(room, tmp_path / "bad", poses="gt", frames=FRAMES, holdout_every=8,
                                     progress=False)
    assert not (tmp_path / "bad").exists()


# ------------------------------------------------------------------------------------------------ the example
@pytest.mark.slow
def test_worked_example_runs(tmp_path):
    """docs/examples/from_python.py, run as a reader would (docs/guides/python_api.md quotes it)."""
    proc = subprocess.run([sys.executable, str(EXAMPLE), str(tmp_path / "out")], capture_output=True, text=True,
                          timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert re.search(r"Reconstruction\(30 of 30 frames fused, L1 mean \d+\.\d+, complete, no files\)", proc.stdout)
    assert re.search(r"mesh: \d+ vertices, \d+ triangles", proc.stdout)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["corrected.png", "crf.npz", "room.ply",
                                                                    "vignetting.npz"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_docs_quote_the_example():
    """The docs' Python API guide (docs/guides/python_api.md) shows docs/examples/from_python.py verbatim (from its
    first import)."""
    page = (ROOT / "docs" / "guides" / "python_api.md").read_text(encoding="utf-8")
    block = re.search(r"```python\n(.*?)```", page, re.S)
    assert block is not None, "docs/guides/python_api.md has no python code block (the example must be quoted there)"
    code = EXAMPLE.read_text(encoding="utf-8")
    assert block.group(1) == code[code.index("import sys"):]
