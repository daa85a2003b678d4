"""A replay (``--config RUN/config.json``) checks what its run read: config.json records a sha256 and the size of every
input file (response, vignetting, poses, intrinsics, exposures) and the frames of the sequence, and a replay that
would read other files or frames stops in one line naming the file, what changed and the fix (before, it ran with
exit 0 and gave other results: a response overwritten with another gamma, L1 mean 37.52 -> 37.75 on the kitchen;
a sequence that grew from 8 to 11 frames fused 11). An option (or SEQUENCE) given on the command line accepts the
file as it is now; a config.json of an older radiomap still replays, with a note.

Also: a compare method folder's config.json says how to replay it, the top-level one records the sequence, and a
run's config.json no longer holds the empty pre-run exposure summary."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from box_room import box_room_sequence, radial_vignetting
from mapping.cli import cli
from mapping.datasets.redwood import write_log_trajectory
from mapping.metrics import format_tum_trajectory
from mapping.replay import file_record
from radiometry.images import write_depth, write_image

W, H = 160, 120
INPUTS = ("response", "vignetting", "poses", "intrinsics", "exposures")


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def write_sequence(path, frames, *, start=0):
    """Frames of the box room as a Redwood folder (color/, depth/ in mm, trajectory.log of every frame)."""
    (path / "color").mkdir(parents=True, exist_ok=True)
    (path / "depth").mkdir(exist_ok=True)
    for i, f in enumerate(frames, start):
        write_image(path / "color" / f"{i:06d}.png", f.rgb)
        write_depth(path / "depth" / f"{i:06d}.png", f.depth, 1000.0)


@pytest.fixture(scope="module")
def box():
    ds, _ = box_room_sequence(n_frames=8, width=W, height=H)
    return ds.frames


def write_inputs(folder, frames, *, gamma=2.2, strength=0.3, k=1.0, fx=None):
    """The input files of a run, one per option of :data:`INPUTS`."""
    folder.mkdir(parents=True, exist_ok=True)
    res = invoke("response", "--gamma", gamma, "-o", folder / "crf.npz", "--force")
    assert res.exit_code == 0, res.output
    np.save(folder / "V.npy", radial_vignetting(H, W, strength))
    stamps = np.arange(len(frames)) / 30.0
    (folder / "traj.txt").write_text(format_tum_trajectory(stamps, np.stack([f.pose for f in frames])))
    K = frames[0].K
    (folder / "intr.txt").write_text(f"{fx or K[0, 0]:.6f} {K[1, 1]:.6f} {K[0, 2]:.6f} {K[1, 2]:.6f}\n")
    (folder / "k.txt").write_text("".join(f"{t:.6f} {k:.4f}\n" for t in stamps))
    return {"response": folder / "crf.npz", "vignetting": folder / "V.npy", "poses": folder / "traj.txt",
            "intrinsics": folder / "intr.txt", "exposures": folder / "k.txt"}


@pytest.fixture(scope="module")
def kit(box, tmp_path_factory):
    """A sequence of 6 frames, the input files and a corrected run that read all of them."""
    root = tmp_path_factory.mktemp("replay")
    write_sequence(root / "seq", box[:6])
    files = write_inputs(root / "models", box[:6])
    run = root / "run1"
    res = invoke("reconstruct", root / "seq", "-o", run, "-r", files["response"], "--vignetting", files["vignetting"],
                 "--poses", files["poses"], "--intrinsics", files["intrinsics"], "--exposures", files["exposures"],
                 "--voxel-size", "0.05", "--depth-max", "4", "--no-progress")
    assert res.exit_code == 0, res.output
    return root, files, run


def config_of(run):
    return json.loads((run / "config.json").read_text())


def test_config_json_records_a_digest_and_the_size_of_every_input_and_the_frames(kit):
    root, files, run = kit
    config = config_of(run)
    assert set(config["inputs"]) == set(INPUTS)
    for name, path in files.items():
        data = path.read_bytes()
        assert config["inputs"][name] == {"path": str(path.absolute()), "sha256": hashlib.sha256(data).hexdigest(),
                                          "bytes": len(data)}
    names = "\n".join(f"color/{i:06d}.png\tdepth/{i:06d}.png" for i in range(6))
    assert config["dataset"]["frames"] == config["dataset"]["sequence_frames"] == 6
    assert config["dataset"]["frame_names_sha256"] == hashlib.sha256(names.encode()).hexdigest()


def test_the_config_holds_no_pre_run_exposure_summary(kit):
    """config.json recorded ``exposure.summary`` as it was before the run (frames 0, every source 0) while
    metrics.json had the run's: the outcome is metrics.json's only now (and the k of a median mesh exposure)."""
    _, _, run = kit
    model = config_of(run)["colour_model"]
    assert model["exposure"]["settings"] and "summary" not in model["exposure"]
    assert model["export_reference"] == {"kind": "median"}
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["colour_model"]["exposure"]["summary"]["frames"] == metrics["frames"]["fused"] == 6
    assert len(metrics["colour_model"]["export_reference"]["k"]) == 3


def replayable_copy(kit, tmp_path, config=None):
    """The run's inputs copied to ``tmp_path`` and its config.json (or ``config``) pointing at the copies (digests
    unchanged)."""
    root, files, run = kit
    config = config or run / "config.json"
    text = config.read_text().replace(str(files["response"].parent), str(tmp_path / "models"))
    shutil.copytree(files["response"].parent, tmp_path / "models")
    (tmp_path / "config.json").write_text(text)
    return tmp_path / "config.json", {k: tmp_path / "models" / v.name for k, v in files.items()}


@pytest.mark.parametrize("name, spelling, same_size", [
    ("response", "--response", False), ("vignetting", "--vignetting", True), ("poses", "--poses", False),
    ("intrinsics", "--intrinsics", True), ("exposures", "--exposures", True)])
def test_a_replay_whose_input_file_changed_is_refused_in_one_line(kit, box, tmp_path, name, spelling, same_size):
    config, copies = replayable_copy(kit, tmp_path)
    changed = {"response": dict(gamma=1.6), "vignetting": dict(strength=0.35), "poses": {},
               "intrinsics": dict(fx=box[0].K[0, 0] * 1.01), "exposures": dict(k=1.1)}[name]
    new = write_inputs(tmp_path / "new", box[:6], **changed)[name]
    if name == "poses":   # the same poses, one line of comment more
        new.write_text("# re-exported\n" + new.read_text())
    before = copies[name].read_bytes()
    shutil.copyfile(new, copies[name])
    assert copies[name].read_bytes() != before and (len(copies[name].read_bytes()) == len(before)) == same_size
    out = tmp_path / "out"
    res = invoke("reconstruct", "--config", config, "-o", out, "--no-progress")
    assert res.exit_code == 1, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1, res.output
    recorded = hashlib.sha256(before).hexdigest()[:12]
    now = hashlib.sha256(copies[name].read_bytes()).hexdigest()[:12]
    assert lines[0].startswith(f"radiomap: error: {config}: {spelling} {copies[name]} changed since the recorded run "
                               f"read it (sha256 {recorded} recorded, {now} now")
    assert (f"{len(before)} bytes recorded" in lines[0]) != same_size
    assert f"restore it, give {spelling} {copies[name]} on the command line to use it as it is now, or run anew " \
           "without --config" in lines[0]
    assert not out.exists()
    if name == "response":   # the option given again: the file as it is now is meant; the run is another one
        res = invoke("reconstruct", "--config", config, "-o", out, spelling, copies[name], "--no-progress")
        assert res.exit_code == 0, res.output
        a = json.loads((kit[2] / "metrics.json").read_text())["histogram"]["mean"]
        b = json.loads((out / "metrics.json").read_text())["histogram"]["mean"]
        assert a != b
        assert config_of(out)["inputs"]["response"]["sha256"].startswith(now)


def test_an_unchanged_replay_runs_and_an_old_config_replays_with_a_note(kit, tmp_path):
    root, files, run = kit
    res = invoke("reconstruct", "--config", run / "config.json", "-o", tmp_path / "same", "--no-progress")
    assert res.exit_code == 0, res.output
    assert "note:" not in res.stderr
    a, b = (json.loads((r / "metrics.json").read_text()) for r in (run, tmp_path / "same"))
    assert a["histogram"] == b["histogram"] and a["frames"] == b["frames"]
    old = config_of(run)
    del old["inputs"], old["dataset"]["frame_names_sha256"], old["dataset"]["sequence_frames"]
    (tmp_path / "old.json").write_text(json.dumps(old))
    res = invoke("reconstruct", "--config", tmp_path / "old.json", "-o", tmp_path / "old", "--no-progress")
    assert res.exit_code == 0, res.output
    assert f"note: {tmp_path / 'old.json'} records no digests of its input files or frames (written by an older " \
           "radiomap): the replay cannot check that they are unchanged" in res.stderr


def test_a_replay_of_a_sequence_whose_frames_changed_is_refused(box, tmp_path):
    """A run of every frame (4) and one of --frames 0:3; the sequence then grows to 6 frames: the first replay is
    refused (4 recorded, 6 now), the second selects the same 3 frames and runs; a renamed frame is refused too; SEQUENCE
    given on the command line fuses the sequence as it is now."""
    seq = tmp_path / "seq"
    write_sequence(seq, box[:4])
    write_log_trajectory(seq / "trajectory.log", [f.pose for f in box[:4]])
    K = box[0].K
    common = ("--poses", "gt", "--intrinsics", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}", "--voxel-size", "0.05",
              "--depth-max", "4", "--no-progress")
    for out, extra in (("all", ()), ("three", ("--frames", "0:3"))):
        res = invoke("reconstruct", seq, "-o", tmp_path / out, *extra, *common)
        assert res.exit_code == 0, res.output
    write_sequence(seq, box[4:6], start=4)
    write_log_trajectory(seq / "trajectory.log", [f.pose for f in box[:6]])
    config = tmp_path / "all" / "config.json"
    res = invoke("reconstruct", "--config", config, "-o", tmp_path / "again", "--no-progress")
    assert res.exit_code == 1, res.output
    assert res.output.strip() == (
        f"radiomap: error: {config}: the sequence {seq.absolute()} now gives 6 frames where the recorded run had 4 "
        f"(frames were added or removed); restore the sequence, give SEQUENCE ({seq.absolute()}) or --frames on the "
        "command line to fuse it as it is now, or run anew without --config")
    assert not (tmp_path / "again").exists()
    res = invoke("reconstruct", "--config", tmp_path / "three" / "config.json", "-o", tmp_path / "three_again",
                 "--no-progress")
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "three_again" / "metrics.json").read_text())["frames"]["fused"] == 3
    res = invoke("reconstruct", seq, "--config", config, "-o", tmp_path / "grown", "--no-progress")
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "grown" / "metrics.json").read_text())["frames"]["fused"] == 6
    for sub in ("color", "depth"):    # the same number of frames under other names
        (seq / sub / "000002.png").rename(seq / sub / "000007.png")
    res = invoke("reconstruct", "--config", tmp_path / "three" / "config.json", "-o", tmp_path / "renamed",
                 "--no-progress")
    assert res.exit_code == 1 and "gives 3 frames as recorded but their file names differ (sha256" in res.output


def test_a_folder_of_pose_files_is_digested_by_its_pose_files(tmp_path):
    for i in range(3):
        (tmp_path / f"frame-{i:06d}.pose.txt").write_text(" ".join(["1"] * 16) + "\n")
    first = file_record(tmp_path)
    (tmp_path / "frame-000000.color.png").write_bytes(b"not a pose")   # not read as poses: no change
    assert file_record(tmp_path) == first and first["files"] == 3 and first["bytes"] == 3 * 32
    (tmp_path / "frame-000001.pose.txt").write_text(" ".join(["2"] * 16) + "\n")
    assert file_record(tmp_path)["sha256"] != first["sha256"]


@pytest.fixture(scope="module")
def comparison(kit, tmp_path_factory):
    """compare none,lut of the kit's sequence, with its poses and intrinsics files."""
    root, files, _ = kit
    out = tmp_path_factory.mktemp("compare") / "cmp"
    res = invoke("compare", root / "seq", "-r", files["response"], "--vignetting-lut", files["vignetting"],
                 "--methods", "none,lut", "--poses", files["poses"], "--intrinsics", files["intrinsics"],
                 "--voxel-size", "0.05", "--depth-max", "4", "--views", "0", "-o", out, "--no-progress")
    assert res.exit_code == 0, res.output
    return out


@pytest.mark.slow
def test_compare_records_its_inputs_and_refuses_a_replay_whose_lut_changed(kit, comparison, tmp_path):
    """compare --config ran with a vignetting LUT overwritten since (the audit: lut+ec 35.10 -> 35.02, exit 0)."""
    top = config_of(comparison)
    assert set(top["inputs"]) == {"response", "vignetting_lut", "poses", "intrinsics"}
    assert top["dataset"]["frames"] == top["dataset"]["sequence_frames"] == 6
    config, copies = replayable_copy(kit, tmp_path, comparison / "config.json")
    res = invoke("compare", "--config", config, "-o", tmp_path / "same", "--views", "0", "--no-progress")
    assert res.exit_code == 0, res.output
    np.save(copies["vignetting"], radial_vignetting(H, W, 0.2))
    res = invoke("compare", "--config", config, "-o", tmp_path / "again", "--no-progress")
    assert res.exit_code == 1 and not (tmp_path / "again").exists()
    assert res.output.startswith(f"radiomap: error: {config}: --vignetting-lut {copies['vignetting']} changed since "
                                 "the recorded run read it (sha256 ")


@pytest.mark.slow
def test_a_method_folder_of_a_comparison_records_plain_json_and_says_how_to_replay(comparison, tmp_path):
    """A method folder's config.json held ``"dataset": "<mapping.compare.run.FixedPoses object at 0x...>"`` and
    reconstruct --config blamed an old radiomap; now it records the method, the sequence and the colour model as
    plain JSON and ``part_of``, and --config names the replay of the comparison."""
    method = config_of(comparison / "lut")
    assert method["part_of"] == str((comparison / "config.json").absolute()) and method["method"]["name"] == "lut"
    assert method["dataset"]["frames"] == 6 and "<" not in json.dumps(method)
    assert method["colour_model"]["vignetting"].startswith("LUTVignetting(160x120")
    assert method["settings"]["poses"].endswith("traj.txt") and method["settings"]["brightness"] == "mean"
    for command in ("reconstruct", "compare"):
        res = invoke(command, "--config", comparison / "lut" / "config.json", "-o", tmp_path / "rep_lut")
        assert res.exit_code == 1 and res.output.strip() == (
            f"radiomap: error: {comparison / 'lut' / 'config.json'}: the record of method 'lut' of a comparison, not a "
            f"run's config; replay the comparison: radiomap compare --config {(comparison / 'config.json').absolute()} "
            "--methods lut -o OUT")
    # a comparison that wrote no config.json (radiomap demo's): nothing to replay but the command
    doc = {**method, "part_of": None}
    (tmp_path / "demo.json").write_text(json.dumps(doc))
    res = invoke("reconstruct", "--config", tmp_path / "demo.json", "-o", tmp_path / "rep_demo")
    assert res.exit_code == 1 and res.output.strip() == (
        f"radiomap: error: {tmp_path / 'demo.json'}: the record of method 'lut' of a comparison that wrote no "
        "replayable config.json (e.g. radiomap demo's), not a run's config; run that command again")
    # a method folder written before (its dataset the repr of a Python object) gets the same advice
    old = {"dataset": "<mapping.compare.run.FixedPoses object at 0x7f>", "colour_model": {}, "backend": {}}
    (tmp_path / "cmp" / "lut").mkdir(parents=True)
    (tmp_path / "cmp" / "lut" / "config.json").write_text(json.dumps(old))
    res = invoke("reconstruct", "--config", tmp_path / "cmp" / "lut" / "config.json", "-o", tmp_path / "rep_old")
    assert res.exit_code == 1 and res.output.strip().endswith(
        f"replay the comparison: radiomap compare --config {tmp_path / 'cmp' / 'config.json'} --methods lut -o OUT")


def test_a_replay_whose_sequence_intrinsics_or_ground_truth_changed_is_refused(box, tmp_path):
    """The files a run reads from the sequence folder itself: its intrinsics file (compared as the K it gives) and its
    ground truth (a sha256 of the selected frames' poses); --intrinsics given on the command line is not compared."""
    seq = tmp_path / "seq"
    write_sequence(seq, box[:3])
    write_log_trajectory(seq / "trajectory.log", [f.pose for f in box[:3]])
    K = box[0].K
    (seq / "intrinsics.K.txt").write_text("\n".join(" ".join(f"{v:.10g}" for v in row) for row in K) + "\n")
    res = invoke("reconstruct", seq, "-o", tmp_path / "run", "--poses", "gt", "--voxel-size", "0.05", "--depth-max",
                 "4", "--no-progress")
    assert res.exit_code == 0, res.output
    config = tmp_path / "run" / "config.json"
    assert config_of(tmp_path / "run")["dataset"]["ground_truth_sha256"]
    edited = K.copy()
    edited[0, 0] *= 1.02
    (seq / "intrinsics.K.txt").write_text("\n".join(" ".join(f"{v:.10g}" for v in row) for row in edited) + "\n")
    res = invoke("reconstruct", "--config", config, "-o", tmp_path / "k", "--no-progress")
    assert res.exit_code == 1 and not (tmp_path / "k").exists()
    assert res.output.strip() == (
        f"radiomap: error: {config}: the sequence {seq.absolute()} now gives intrinsics {edited[0, 0]:.6g},{K[1, 1]:.6g},"
        f"{K[0, 2]:.6g},{K[1, 2]:.6g} where the recorded run had {K[0, 0]:.6g},{K[1, 1]:.6g},{K[0, 2]:.6g},"
        f"{K[1, 2]:.6g} (its intrinsics file changed); restore it, give --intrinsics on the command line, or run anew "
        "without --config")
    values = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"
    res = invoke("reconstruct", "--config", config, "-o", tmp_path / "given", "--intrinsics", values, "--no-progress")
    assert res.exit_code == 0, res.output
    poses = [f.pose.copy() for f in box[:3]]
    poses[1][0, 3] += 0.01
    write_log_trajectory(seq / "trajectory.log", poses)
    res = invoke("reconstruct", "--config", config, "-o", tmp_path / "gt", "--intrinsics", values, "--no-progress")
    assert res.exit_code == 1 and not (tmp_path / "gt").exists()
    assert f"the ground-truth poses of the sequence {seq.absolute()} differ from the recorded run's (sha256" \
        in res.output
