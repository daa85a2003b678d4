"""``config.json`` holds plain values, and ``radiomap reconstruct|compare --config RUN/config.json`` replays a run
with the same results; command-line options override the file; a file that cannot be replayed is one line."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from mapping.cli import cli


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def room():
    from mapping.simulation import sample_sequence

    return sample_sequence("room")


@pytest.fixture(scope="module")
def first_run(room, tmp_path_factory):
    """A corrected reconstruction (response, vignetting, exposure compensation by default) at ground-truth poses."""
    out = tmp_path_factory.mktemp("config") / "run1"
    res = invoke("reconstruct", room, "-o", out, "--response", room / "truth" / "response.npz",
                 "--vignetting", room / "truth" / "vignetting.npy", "--poses", "gt", "--frames", "0:8",
                 "--voxel-size", "0.03", "--depth-max", "4", "--display-exposure", "0.9", "--no-progress")
    assert res.exit_code == 0, res.output
    return out


def assert_plain_json(value, where="config.json"):
    """Only JSON's own types, and no Python repr of an object in a string."""
    if isinstance(value, dict):
        for k, v in value.items():
            assert isinstance(k, str), where
            assert_plain_json(v, f"{where}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            assert_plain_json(v, f"{where}[{i}]")
    else:
        assert value is None or isinstance(value, (bool, int, float, str)), (where, value)
        if isinstance(value, str):
            assert not any(r in value for r in ("slice(", "Path(", "array(", "<")), (where, value)


def metrics(run):
    return json.loads((run / "metrics.json").read_text())


@pytest.mark.slow
def test_config_json_holds_plain_values_that_the_options_read_back(first_run, room):
    config = json.loads((first_run / "config.json").read_text())
    assert_plain_json(config)
    p = config["parameters"]
    assert config["command"] == "reconstruct" and config["config_version"] == 1
    assert p["frames"] == "0:8" and p["sequence"] == str(room.absolute()) and p["voxel_size"] == 0.03
    assert p["display_exposure"] == 0.9 and p["mesh_exposure"] is None and p["exposure_compensation"] is None
    assert not {"force", "no_progress", "config"} & set(p)          # how to run, not what was run
    assert config["argv"][:3] == ["radiomap", "reconstruct", str(room)]
    assert config["pipeline"]["frames"] == "0:8" and config["pipeline"]["reference_exposure"] == 0.9


@pytest.mark.slow
def test_reconstruct_replay_gives_the_same_metrics(first_run, tmp_path):
    replay = tmp_path / "replay"
    res = invoke("reconstruct", "--config", first_run / "config.json", "-o", replay, "--no-progress")
    assert res.exit_code == 0, res.output
    a, b = metrics(first_run), metrics(replay)
    assert a["frames"]["fused"] == b["frames"]["fused"] == 8
    assert a["histogram"] == b["histogram"] and a["histogram"]["count"] > 0
    assert a["ate"] == b["ate"]
    assert a["colour_model"] == b["colour_model"]
    old = json.loads((first_run / "config.json").read_text())
    new = json.loads((replay / "config.json").read_text())
    assert {k: v for k, v in new["parameters"].items() if k != "output"} == \
        {k: v for k, v in old["parameters"].items() if k != "output"}
    assert new["parameters"]["output"] == str(replay) and new["replay_of"] == str(first_run / "config.json")
    # the summary (printed and saved) says where each setting came from
    summary = (replay / "summary.txt").read_text()
    assert f"poses gt (from {first_run / 'config.json'})" in summary
    assert "exposure compensation on (reconstruct's default with --response; compare's is off)" in summary
    assert summary.splitlines()[-1] in res.output


@pytest.mark.slow
def test_icp_run_replays_to_the_same_trajectory(room, tmp_path):
    """With ICP the replay tracks again: the same frames fused and the same ATE and histogram up to the noise of
    Open3D's threaded reductions (measured: ATE within 0.005 mm, L1 mean within 0.02 %, pairs within 0.003 %)."""
    first = tmp_path / "icp"
    res = invoke("reconstruct", room, "-o", first, "--response", room / "truth" / "response.npz", "--frames",
                 "0:6", "--voxel-size", "0.03", "--depth-max", "4", "--no-progress")
    assert res.exit_code == 0, res.output
    res = invoke("reconstruct", "--config", first / "config.json", "-o", tmp_path / "again", "--no-progress")
    assert res.exit_code == 0, res.output
    a, b = metrics(first), metrics(tmp_path / "again")
    assert a["frames"]["fused"] == b["frames"]["fused"] == 6
    assert a["ate"]["rmse"] == pytest.approx(b["ate"]["rmse"], abs=1e-4)
    assert a["histogram"]["mean"] == pytest.approx(b["histogram"]["mean"], rel=1e-3)
    assert a["histogram"]["count"] == pytest.approx(b["histogram"]["count"], rel=1e-3)
    assert "poses icp (from" in (tmp_path / "again" / "summary.txt").read_text()


@pytest.mark.slow
def test_command_line_overrides_the_config_and_a_replay_does_not_overwrite(first_run, tmp_path):
    before = (first_run / "metrics.json").read_bytes()
    res = invoke("reconstruct", "--config", first_run / "config.json", "--no-progress")   # -o from the file
    assert res.exit_code == 1 and "already holds the results of a run; pass --force" in res.output
    assert (first_run / "metrics.json").read_bytes() == before
    out = tmp_path / "coarse"
    res = invoke("reconstruct", "--config", first_run / "config.json", "-o", out, "--frames", "0:8:2",
                 "--no-exposure-compensation", "--no-progress")
    assert res.exit_code == 0, res.output
    p = json.loads((out / "config.json").read_text())["parameters"]
    assert p["frames"] == "0:8:2" and p["exposure_compensation"] is False and p["voxel_size"] == 0.03
    assert metrics(out)["frames"]["total"] == 4
    assert "exposure compensation off (given)" in (out / "summary.txt").read_text()


@pytest.mark.slow
def test_a_recorded_value_the_command_line_contradicts_is_dropped_with_a_note(first_run, tmp_path):
    """The command line cannot unset a recorded --mesh-exposure or --surfel-mesh: an override that contradicts
    one drops it (a note names the file and the key); the same contradiction typed out is still refused."""
    recorded = rewrite(first_run / "config.json", tmp_path,
                       lambda d: d["parameters"].update(mesh_exposure="first", frames="0:3"))
    out = tmp_path / "no_ec"
    res = invoke("reconstruct", "--config", recorded, "-o", out, "--no-exposure-compensation", "--no-progress")
    assert res.exit_code == 0, res.output
    assert f"note: {recorded}: mesh_exposure 'first' is not used (no exposure compensation)" in res.stderr
    p = json.loads((out / "config.json").read_text())["parameters"]
    assert p["mesh_exposure"] is None and p["exposure_compensation"] is False
    res = invoke("reconstruct", "--config", recorded, "-o", tmp_path / "typed", "--no-exposure-compensation",
                 "--mesh-exposure", "first")
    assert res.exit_code == 2 and "applies with exposure compensation only" in res.output
    # a TSDF run's recorded --formats glb replayed with --backend surfel (which writes PLY only) is dropped too
    recorded = rewrite(first_run / "config.json", tmp_path,
                       lambda d: d["parameters"].update(formats=["ply", "glb"], frames="0:3"))
    res = invoke("reconstruct", "--config", recorded, "-o", tmp_path / "surfel", "--backend", "surfel",
                 "--no-progress")
    assert res.exit_code == 0, res.output
    assert f"note: {recorded}: formats ('ply', 'glb') is not used (--backend surfel)" in res.stderr, res.stderr
    assert json.loads((tmp_path / "surfel" / "config.json").read_text())["parameters"]["formats"] == ["ply"]


@pytest.mark.slow
def test_compare_replay_gives_the_same_table(room, tmp_path):
    out = tmp_path / "cmp"
    res = invoke("compare", room, "-r", room / "truth" / "response.npz", "--vignetting-lut",
                 room / "truth" / "vignetting.npy", "--methods", "none,lut", "--frames", "0:6", "--voxel-size",
                 "0.04", "--depth-max", "4", "--views", "0", "-o", out, "--formats", "ply,glb", "--no-progress")
    assert res.exit_code == 0, res.output
    config = json.loads((out / "config.json").read_text())
    assert_plain_json(config)
    assert config["parameters"]["methods"] == "none,lut" and config["methods_run"] == ["none", "lut"]
    assert config["parameters"]["formats"] == ["ply", "glb"] and (out / "lut" / "mesh.glb").is_file()
    summary = (out / "summary.txt").read_text()
    assert "poses gt (compare's default; reconstruct's is icp)" in summary and "formats ply,glb (given)" in summary
    res = invoke("compare", "--config", out / "config.json", "-o", tmp_path / "again", "--no-progress")
    assert res.exit_code == 0, res.output
    table = [{k: v for k, v in row.items() if k != "seconds"}
             for row in json.loads((out / "compare.json").read_text())["table"]]
    again = [{k: v for k, v in row.items() if k != "seconds"}
             for row in json.loads((tmp_path / "again" / "compare.json").read_text())["table"]]
    assert table == again and len(table) == 2
    res = invoke("compare", "--config", out / "config.json", "--no-progress")   # into the same folder
    assert res.exit_code == 1 and "--force" in res.output


def rewrite(config_file, tmp_path, change):
    doc = json.loads(config_file.read_text())
    change(doc)
    path = tmp_path / "edited.json"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.slow
@pytest.mark.parametrize("change, key, fix", [
    (lambda d: d["parameters"].update(colour="lut"), "'parameters.colour'", "remove or rename it"),
    (lambda d: d["parameters"].update(reference_exposure=2.0), "'parameters.reference_exposure' for radiomap "
     "reconstruct (renamed 'display_exposure')", "rename it"),
    (lambda d: d.update(voxel_size=0.1), "unknown key 'voxel_size' (options go under 'parameters')", "remove it"),
    (lambda d: d.update(config_version=2), "key 'config_version' is 2", "replays version 1"),
    (lambda d: (d.pop("config_version"), d["parameters"].update(frames="slice(None, None, None)")),
     "no key 'config_version'", "give its options on the command line"),
    (lambda d: d.update(command="compare"), "key 'command' is 'compare'", "radiomap compare --config"),
    (lambda d: d["parameters"].update(voxel_size="fine"), "key 'parameters.voxel_size'", "--voxel-size"),
    (lambda d: d["parameters"].update(force=True), "'parameters.force'", "give it on the command line"),
])
def test_a_config_that_cannot_be_replayed_is_one_line(first_run, tmp_path, change, key, fix):
    path = rewrite(first_run / "config.json", tmp_path, change)
    res = invoke("reconstruct", "--config", path, "-o", tmp_path / "out", "--no-progress")
    assert res.exit_code == 1, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"radiomap: error: {path}: "), res.output
    assert key in lines[0] and fix in lines[0]
    assert not (tmp_path / "out").exists()


def test_not_json_is_one_line(tmp_path):
    path = tmp_path / "config.json"
    path.write_text("{not json")
    res = invoke("compare", "--config", path, "-o", tmp_path / "out")
    assert res.exit_code == 1 and res.output.startswith(f"radiomap: error: {path}: not a JSON file")


def test_old_spellings_still_work_and_warn(room, tmp_path):
    out = tmp_path / "old"
    res = invoke("reconstruct", room, "-o", out, "-r", room / "truth" / "response.npz", "-v",
                 room / "truth" / "vignetting.npy", "--reference-exposure", "0.5", "--exposure-reference", "first",
                 "--poses", "gt", "--frames", "0:3", "--voxel-size", "0.05", "--depth-max", "4", "--no-progress")
    assert res.exit_code == 0, res.output
    for line in ("warning: -v is deprecated, use --vignetting (-v is radiomap's --verbose",
                 "warning: --reference-exposure is deprecated, use --display-exposure",
                 "warning: --exposure-reference is deprecated, use --mesh-exposure"):
        assert line in res.stderr
    p = json.loads((out / "config.json").read_text())["parameters"]
    assert p["display_exposure"] == 0.5 and p["mesh_exposure"] == "first"
    assert p["vignetting"] == str((room / "truth" / "vignetting.npy").absolute())
    # the old and the new spelling together: which one is meant?
    res = invoke("reconstruct", room, "-o", tmp_path / "both", "--reference-exposure", "0.5",
                 "--display-exposure", "0.7")
    assert res.exit_code == 2 and "--reference-exposure is the old spelling of --display-exposure" in res.output
    # an old spelling's value is checked like the new one's
    res = invoke("reconstruct", room, "-o", tmp_path / "neg", "--reference-exposure", "-1")
    assert res.exit_code == 1 and "--reference-exposure" in res.output and "outside the sensible range" in res.output
    res = invoke("reconstruct", room, "-o", tmp_path / "raw", "--mesh-exposure", "first")
    assert res.exit_code == 2 and "applies with exposure compensation only" in res.output
