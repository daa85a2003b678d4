"""``radiomap demo --quick``: the whole method on a simulated camera, as CI runs it (one shared run)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from test_report import check_report


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """One ``radiomap demo --quick`` run (CLI, in-process), started in an empty working directory so that
    nothing from the checkout can be used."""
    from click.testing import CliRunner

    from mapping.cli import cli

    work = tmp_path_factory.mktemp("demo_cwd")
    old = os.getcwd()
    os.chdir(work)
    try:
        res = CliRunner().invoke(cli, ["demo", "--quick", "-o", "out", "--no-progress"])
    finally:
        os.chdir(old)
    assert res.exit_code == 0, res.output
    out = work / "out"
    doc = json.loads((out / "demo.json").read_text())
    compare_doc = json.loads((out / "compare" / "compare.json").read_text())
    return {"work": work, "out": out, "output": res.output, "demo": doc, "compare": compare_doc,
            "table": {row["method"]: row for row in compare_doc["table"]}}


def _name(table: dict, base: str) -> str:
    return next(n for n in table if n.removesuffix("+ec") == base)


@pytest.mark.slow
def test_methods_are_ordered_as_in_the_paper(demo):
    """No correction worst, LUT best on the L1 mean. Measured (quick demo, 'asymmetric' camera, seed 0,
    exposure compensation on; the response by the default method, loglog): none 26.21, response+ec 25.89,
    poly+ec 15.94, lut+ec 15.88. The LUT's lead
    on the L1 mean is small although the polynomial misses V by 2.5 % RMS: a point keeps nearly the same image
    position over a short handheld sequence, so a smooth residual largely cancels between the map and the new
    sample, and the L1 mean adds such errors to the noise floor only at second order; the colour error
    against the truth below separates the two at first order. The paper's methods only: the self-calibrated
    method ties the LUT on the L1 mean (15.85), see the test after the next."""
    table = demo["table"]
    l1 = {name: row["L1 mean"] for name, row in table.items() if not name.startswith("self")}
    assert max(l1, key=l1.get) == "none"
    assert min(l1, key=l1.get) == _name(table, "lut")
    ranking = [n for n in demo["demo"]["ranking_l1_mean"] if not n.startswith("self")]
    assert ranking[0] == _name(table, "lut") and ranking[-1] == "none"
    # vignetting correction is what makes the difference (not the response or exposure alone)
    lut, poly = _name(table, "lut"), _name(table, "poly")
    resp = _name(table, "response")
    assert l1["none"] > 1.25 * l1[lut] and l1[resp] > 1.25 * l1[poly]
    assert table["none"]["L1 p90"] > table[lut]["L1 p90"]


@pytest.mark.slow
def test_mesh_colours_against_the_truth_follow_the_same_order(demo):
    table = demo["table"]
    err = {name: row["colour err"] for name, row in table.items()}
    lut, poly, resp = _name(table, "lut"), _name(table, "poly"), _name(table, "response")
    assert err[lut] < err[poly] < err[resp]
    assert err[poly] > 1.1 * err[lut]          # measured 4.31 vs 3.58: the non-radial field the polynomial misses
    assert err["none"] > 2.0 * err[lut]
    assert err[lut] < 5.0


@pytest.mark.slow
def test_self_calibrated_method_is_near_the_lut_and_ahead_of_the_polynomial(demo):
    """V from the room's own 15 frames (1.3-1.75 levels off the truth, the LUT 0.26-0.29, the polynomial 2.5-2.9):
    measured L1 mean 15.87 (LUT 15.89, polynomial 15.96), colour error 3.98 (LUT 3.58, polynomial 4.31). Since issue
    29 (the grid follows the coverage, the tilt is free where the data pin it, V fitted on 12 of the 15 frames, the
    others withheld to validate it) the self-calibrated method's colour error came out 4.31 against the LUT's 4.53:
    near the LUT, on either side of it."""
    table = demo["table"]
    l1 = {name: row["L1 mean"] for name, row in table.items()}
    err = {name: row["colour err"] for name, row in table.items()}
    lut, poly = _name(table, "lut"), _name(table, "poly")
    assert abs(l1["self+ec"] - l1[lut]) < 0.01 * l1[lut] and l1["self+ec"] < l1[poly]
    assert err["self+ec"] < err[poly] and abs(err["self+ec"] - err[lut]) < 0.15 * err[lut]


@pytest.mark.slow
def test_calibration_is_accurate(demo):
    cal = demo["demo"]["calibration"]
    assert max(cal["response_error_percent"]) < 3.0
    lut, poly = np.array(cal["vignetting_error_levels"]["lut"]), np.array(cal["vignetting_error_levels"]["poly"])
    # measured LUT 0.28 / 0.29 / 0.26, polynomial 2.86 / 2.72 / 2.51 levels: the polynomial cannot follow the
    # 'asymmetric' camera's non-radial field (the free-centre fit is within 1 level on the nearly radial xtion)
    assert np.all(lut < 0.5) and np.all(poly > 5 * lut) and np.all(poly < 4.0)
    assert cal["paper_frames_used"] >= 50


@pytest.mark.slow
def test_report_opens_with_every_image(demo):
    report = demo["out"] / demo["demo"]["report"]
    images, links = check_report(report)
    ec = demo["demo"]["exposure_compensation"]
    assert images == 4 + int(ec)   # histograms, colour error, renders, trajectory (+ exposure estimates)
    text = report.read_text(encoding="utf-8")
    assert "Calibration accuracy" in text and "Exposure compensation: O" in text
    assert ("Exposure compensation: ON" in text) == ec


@pytest.mark.slow
def test_prints_the_table_calibration_and_report_path(demo):
    out = demo["output"]
    assert "Calibration accuracy" in out and "% of range" in out and "8-bit levels" in out
    assert "ranking by L1 mean (best first):" in out
    assert "report: out/compare/report.html" in out
    for name in demo["table"]:
        assert f"\n{name} " in out
    assert (demo["out"] / "demo.txt").read_text().strip() in out   # demo.txt is what was printed


@pytest.mark.slow
def test_everything_is_written_into_out_only(demo):
    out = demo["out"]
    assert sorted(p.name for p in demo["work"].iterdir()) == ["out"]
    for rel in ("calibration/response.npz", "calibration/vignetting_lut.npz", "calibration/vignetting_poly.npz",
                "calibration/camera.json", "sequence/radiomap_sequence.json", "sequence/truth/room.json",
                "compare/histograms.png", "compare/renders.jpg", "compare/compare.csv", "demo.json", "demo.txt"):
        assert (out / rel).is_file(), rel
    for name in demo["table"]:   # the meshes of the uncorrected map and the LUT correction (--all-meshes: all)
        assert (out / "compare" / name / "mesh.ply").is_file() == (name.split("+")[0] in ("none", "lut")), name
        assert not (out / "compare" / name / "mesh_colours.npz").exists() and not (out / "compare" / name /
                                                                                   "mesh.glb").exists()
    assert demo["compare"]["poses_identical"] is True
    assert demo["demo"]["quick"] is True and demo["demo"]["size"]["width"] == 160
    assert demo["demo"]["camera"] == "asymmetric" and "asymmetric preset" in demo["output"]
    assert demo["demo"]["seconds"] > 0 and set(demo["demo"]["timings"]) == {"response", "vignetting", "room",
                                                                           "self_calibration", "compare"}


@pytest.mark.slow
def test_quick_demo_has_the_self_calibrated_method(demo):
    """V self-calibrated from the quick demo's own 15 frames (160x120): its row in the calibration table, its
    method in the comparison, its folder with the standard error. Measured with window 3 on this room: 1.3-1.75
    levels (the 5 px window of the first version rejected every point in the top third at 160x120 and the quick
    demo had no self method)."""
    err = np.array(demo["demo"]["calibration"]["vignetting_error_levels"]["self"])
    assert err.shape == (3,) and np.all(err < 3.0), err
    assert "self+ec" in demo["table"] and "self-calibrated from the room (15 frames)" in demo["output"]
    record = demo["demo"]["calibration"]["self_calibration"]
    assert 0 < record["stderr_median_percent"] < 5 and record["frames"] == 15
    assert (demo["out"] / "calibration" / "self" / "stderr.png").is_file()


@pytest.mark.slow
def test_a_room_that_cannot_constrain_v_is_run_without_the_self_method(tmp_path):
    """Step 5 on 8 frames at 64x48: self-calibration refuses with its one-line reason, which the demo keeps
    (and prints) instead of a model."""
    from mapping.demo import _self_calibrate
    from mapping.simulation.sequences import simulate_room
    from radiometry.simulation import CameraSpec, SimulatedCamera

    sim = SimulatedCamera(CameraSpec.preset("xtion", width=64, height=48))
    seq = simulate_room(tmp_path / "room", camera=sim.spec, seed=2, n_frames=8, progress=False)
    timings, lines = {}, []
    model, record = _self_calibrate(tmp_path / "calib", seq, sim, sim.response, progress=False, timings=timings,
                                    say=lines.append)
    assert model is None and "cannot constrain vignetting" in record["skipped"]
    assert lines == [f"self-calibration: skipped, {record['skipped']}"] and timings["self_calibration"] > 0


@pytest.mark.slow
def test_self_calibration_step_on_a_room_it_can_constrain(tmp_path):
    """The demo's step 5 on a room that constrains V (160x120, 30 frames, seed 1: measured 0.43 / 0.37 / 0.95
    levels and exposure median 1.4 % with the true response): V's error against the truth in the calibration
    table's measure, the stderr recorded, and the model the compare method takes."""
    from mapping.demo import _self_calibrate
    from mapping.simulation.sequences import simulate_room
    from mapping.simulation.trajectory import HandheldMotion
    from radiometry.simulation import CameraSpec, SimulatedCamera
    from radiometry.vignetting import LUTVignetting

    sim = SimulatedCamera(CameraSpec.preset("asymmetric", width=160, height=120))
    seq = simulate_room(tmp_path / "room", camera=sim.spec, seed=1, n_frames=30, width=160, height=120,
                        motion=HandheldMotion(speed=3.0), progress=False)
    timings, lines = {}, []
    model, record = _self_calibrate(tmp_path / "calib", seq, sim, sim.response, progress=False, timings=timings,
                                    say=lines.append)
    assert isinstance(model, LUTVignetting) and model.stderr is not None
    err = np.array(record["vignetting_error_levels"])
    assert err.shape == (3,) and np.all(err < 1.5), err
    # 2.0 % since issue 29 (V fitted on 24 of the 30 frames, every 5th withheld to validate it; 1.4 % before)
    assert record["exposure_error_median_percent"] < 2.5
    assert 0 < record["stderr_median_percent"] < 5 and record["frames"] == 30 and timings["self_calibration"] > 0
    assert (tmp_path / "calib" / "self" / "vignetting.npz").is_file() and "self-calibration: V" in lines[0]


@pytest.mark.slow
def test_self_method_takes_the_self_calibrated_lut():
    from mapping.compare import make_methods
    from radiometry.response import CameraResponse
    from radiometry.vignetting import LUTVignetting, PolynomialVignetting

    resp = CameraResponse.gamma(2.2)
    lut = LUTVignetting(np.ones((12, 16, 3), np.float32))
    (m,) = make_methods(resp, vignetting_self=lut, names=["self+ec"])
    assert m.vignetting is lut and m.exposure_compensation and m.label.startswith("self-calibrated vignetting")
    with pytest.raises(ValueError, match="needs the self vignetting model .*radiomap self-calibrate"):
        make_methods(resp, vignetting_lut=lut, names=["self"])
    poly = PolynomialVignetting([0.0, 0.0, 0.0], [7.5, 5.5], (16, 12))
    with pytest.raises(ValueError, match="--vignetting-self holds a polynomial .* --vignetting-poly"):
        make_methods(resp, vignetting_self=poly, names=["self"])


@pytest.mark.slow
def test_models_written_by_the_demo_load(demo):
    from radiometry.response import CameraResponse
    from radiometry.vignetting import LUTVignetting, PolynomialVignetting, VignettingModel

    cal = demo["out"] / "calibration"
    assert CameraResponse.load(cal / "response.npz").channels == 3
    assert isinstance(VignettingModel.load(cal / "vignetting_lut.npz"), LUTVignetting)
    assert isinstance(VignettingModel.load(cal / "vignetting_poly.npz"), PolynomialVignetting)


# --------------------------------------------------------------------------------------------------
# the output-folder policy (cheap: no demo run)
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_demo_replaces_only_its_own_earlier_outputs(tmp_path):
    from mapping.demo import DemoFolder
    from mapping.export import LOCK_NAME, RUNNING_MARKER
    from radiometry.errors import OutputError

    def prepare(folder, *, force):
        with DemoFolder(folder, force=force) as demo_folder:
            demo_folder.complete()

    out = tmp_path / "d"
    (out / "compare" / "none").mkdir(parents=True)
    (out / "compare" / "none" / "mesh.ply").write_text("old")
    (out / "demo.json").write_text("{}")
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match=f"^{out} holds an earlier demo; pass --force to overwrite it or choose "
                                          "another folder$"):
        prepare(out, force=False)
    assert (out / "compare" / "none" / "mesh.ply").read_text() == "old" and (out / "demo.json").is_file()
    prepare(out, force=True)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    with pytest.raises(OutputError, match="holds no earlier demo"):
        prepare(out, force=False)
    prepare(out, force=True)
    assert (out / "notes.txt").read_text() == "mine"
    # an interrupted demo (RUNNING, no demo.json) is an earlier demo too, its folders removed with --force
    DemoFolder(out, force=True).release()
    (out / "sequence" / "rgb").mkdir(parents=True)
    assert sorted(p.name for p in out.iterdir()) == [RUNNING_MARKER, "notes.txt", "sequence"]
    with pytest.raises(OutputError, match="holds an unfinished demo \\(interrupted or failed"):
        prepare(out, force=False)
    prepare(out, force=True)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputError, match="existing file"):
        prepare(tmp_path / "f", force=True)
    prepare(tmp_path / "new", force=False)
    assert (tmp_path / "new").is_dir() and not any((tmp_path / "new").iterdir())
    assert not (out / LOCK_NAME).exists()


@pytest.mark.slow
def test_demo_run_twice_needs_force(demo):
    """`radiomap demo -o OUT` onto an earlier demo: one line naming OUT and the fix, exit 1, every file of the
    earlier demo byte-identical (calibrations included)."""
    from click.testing import CliRunner

    from mapping.cli import cli

    out = demo["out"]
    before = {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    assert out / "calibration" / "response.npz" in before
    res = CliRunner().invoke(cli, ["demo", "--quick", "-o", str(out), "--no-progress"])
    assert res.exit_code == 1, res.output
    assert res.output.strip().splitlines() == [
        f"radiomap: error: {out} holds an earlier demo; pass --force to overwrite it or choose another folder"]
    assert {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before


def test_response_error_measure():
    from mapping.demo import response_error_percent
    from radiometry.response import CameraResponse

    g = CameraResponse.gamma(2.2)
    assert response_error_percent(g, g) == [0.0, 0.0, 0.0]
    err = response_error_percent(CameraResponse.gamma(2.0), g)
    lv = np.arange(5, 251) / 255.0
    assert err[0] == pytest.approx(100 * np.max(np.abs(lv ** 2.0 - lv ** 2.2)), rel=1e-6)
