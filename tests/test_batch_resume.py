"""A resumed ``radiomap batch`` reports only results made by this batch's command, sequence and options
(mapping.batch.resume): a complete folder made with other options is refused before anything runs (--force runs
it again); a folder keeps its name when the list gains a sequence of the same folder name, and folders no listed
sequence takes are named; a finished folder with a listed file missing, empty or unreadable is run again, naming
the file; the summary's time columns say what they measure."""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mapping.batch import COMMANDS, BatchError, Task, folder_names, run_batch, task_names
from mapping.batch.resume import changed_options, damage, mismatch, recorded_run, refusal

W, H = 64, 48
RADIOMAP = [sys.executable, "-c", "import sys; from mapping.cli import main; sys.exit(main())"]


def _options(data, voxel: str = "0.05") -> list[str]:
    return ["--poses", "gt", "-r", str(data["crf"]), "--depth-max", "6", "--voxel-size", voxel]


def _batch(listing: Path, out: Path, options: list[str], *extra: str, command: str = "reconstruct"):
    return subprocess.run([*RADIOMAP, "batch", command, str(listing), "-o", str(out), "--engine", "processes",
                           "--workers", "2", "--no-progress", *extra, "--", *options],
                          capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two short simulated rooms in seqs/ (alpha, beta), a third room also named alpha in other/, the list of the
    first two, a response file, and the batch of the two made once (copied by each test that resumes it)."""
    from mapping.simulation.sequences import simulate_room
    from radiometry.response import CameraResponse
    from radiometry.simulation import CameraSpec

    root = tmp_path_factory.mktemp("resume")
    seqs = {}
    for key, folder, seed in (("alpha", root / "seqs" / "alpha", 1), ("beta", root / "seqs" / "beta", 2),
                              ("other", root / "other" / "alpha", 3)):
        seqs[key] = simulate_room(folder, camera=CameraSpec.preset("xtion", width=W, height=H), seed=seed,
                                  n_frames=6, progress=False)
    listing = root / "list.txt"
    listing.write_text(f"{seqs['alpha']}\n{seqs['beta']}\n")
    crf = root / "crf.npz"
    CameraResponse.gamma().save(crf)
    data = {"root": root, "seqs": seqs, "list": listing, "crf": crf}
    res = _batch(listing, root / "made", _options(data))
    assert res.returncode == 0, res.stderr
    data["made"] = root / "made"
    return data


def _resumable(data, tmp_path) -> Path:
    out = tmp_path / "out"
    shutil.copytree(data["made"], out, symlinks=True)
    return out


def _stamps(out: Path) -> dict[str, int]:
    return {str(p.relative_to(out)): p.stat().st_mtime_ns for p in sorted(out.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------ item 1: changed options
def test_changed_options_compares_what_changes_results():
    old = {"command": "reconstruct", "parameters": {"sequence": "/s/a", "output": "/o/a", "voxel_size": 0.04,
                                                    "response": "/m/crf.npz", "formats": ["ply"], "gone": 1}}
    new = {"command": "reconstruct", "parameters": {"sequence": "/s/a", "output": "/elsewhere/a", "voxel_size": 0.02,
                                                    "response": None, "formats": ("ply",), "added": 2}}
    # the place is not compared, a tuple equals its JSON list, an option only one record holds is not compared
    assert changed_options(old, new) == [("voxel_size", 0.04, 0.02), ("response", "/m/crf.npz", None)]
    why = mismatch(Path("/o/a"), "reconstruct", Path("/s/a"), old, new)
    assert why == "made with other options (--voxel-size 0.04 -> 0.02; --response /m/crf.npz -> not given)"
    assert mismatch(Path("/o/a"), "compare", Path("/s/a"), old, new) == "it holds a reconstruct run, not compare"
    assert "holds the results of /s/a, not of /s/b" in mismatch(Path("/o/a"), "reconstruct", Path("/s/b"), old, None)
    same = {**new, "parameters": {**old["parameters"], "output": "/x"}}
    assert changed_options(old, same) == [] and mismatch(Path("/o/a"), "reconstruct", Path("/s/a"), old, same) is None
    # digests of the inputs, where both records hold them
    assert changed_options({**old, "input_sha256": {"response": "ab"}}, {**same, "input_sha256": {"response": "cd"}}) \
        == [("input_sha256", "recorded contents", "other contents")]
    line = refusal([(Path("/o/a"), "made with other options (--voxel-size 0.04 -> 0.02)"), (Path("/o/b"), "x")])
    assert "\n" not in line and "(b)" in line and "another -o" in line and "--force" in line
    assert line.startswith("/o/a: complete, but made with other options (--voxel-size 0.04 -> 0.02)")


@pytest.mark.slow
def test_a_resume_with_other_options_is_refused_before_anything_runs(data, tmp_path):
    out = _resumable(data, tmp_path)
    before = _stamps(out)
    summary = (out / "summary.csv").read_bytes()
    res = _batch(data["list"], out, _options(data, voxel="0.04"))
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith(f"radiomap: error: {out / 'alpha'}: complete, but made with other options "
                               "(--voxel-size 0.05 -> 0.04)") and "(beta)" in lines[0]
    assert "another -o" in lines[0] and "--force" in lines[0]
    assert _stamps(out) == before and (out / "summary.csv").read_bytes() == summary   # nothing ran, nothing written
    # without a response (and its exposure compensation): refused too, naming the option
    res = _batch(data["list"], out, ["--poses", "gt", "--depth-max", "6", "--voxel-size", "0.05"])
    assert res.returncode == 1 and f"--response {data['crf']} -> not given" in res.stderr
    # an option that does not change the results (the command's own --no-progress): skipped as before
    res = _batch(data["list"], out, [*_options(data), "--no-progress"])
    assert res.returncode == 0 and res.stdout.count("skipped, complete in") == 2, res.stderr
    # --force runs them again with the new options
    res = _batch(data["list"], out, _options(data, voxel="0.04"), "--force")
    assert res.returncode == 0, res.stderr
    for name in ("alpha", "beta"):
        assert json.loads((out / name / "config.json").read_text())["parameters"]["voxel_size"] == 0.04
    res = _batch(data["list"], out, _options(data, voxel="0.04"))
    assert res.returncode == 0 and res.stdout.count("skipped, complete in") == 2
    # the response rewritten under the same path (its contents are recorded: mapping.replay): refused, naming it
    from radiometry.response import CameraResponse

    CameraResponse.gamma(1.8).save(data["crf"].with_name("crf18.npz"))
    shutil.copyfile(data["crf"], tmp_path / "crf_saved.npz")
    try:
        shutil.copyfile(data["crf"].with_name("crf18.npz"), data["crf"])
        res = _batch(data["list"], out, _options(data, voxel="0.04"))
        assert res.returncode == 1, res.stdout
        assert f"--response {data['crf']} (sha256 " in res.stderr and "-> other contents" in res.stderr, res.stderr
    finally:
        shutil.copyfile(tmp_path / "crf_saved.npz", data["crf"])


def test_a_folder_of_another_sequence_or_command_is_refused(tmp_path):
    """run_batch itself (not only the CLI) refuses a folder whose record names another sequence or command."""
    folder = tmp_path / "out" / "alpha"
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"command": "compare", "parameters": {
        "sequence": str(tmp_path / "seqs" / "alpha")}}))
    task = Task("alpha", "reconstruct", tmp_path / "seqs" / "alpha", folder, {"manifest": {"parameters": {}}})
    with pytest.raises(BatchError, match=r"alpha: complete, but it holds a compare run, not reconstruct; .*another -o"):
        run_batch([task], tmp_path / "out", engine="processes")
    (folder / "config.json").write_text(json.dumps({"command": "reconstruct", "parameters": {
        "sequence": str(tmp_path / "seqs" / "beta")}}))
    with pytest.raises(BatchError, match=r"holds the results of .*beta, not of .*alpha"):
        run_batch([task], tmp_path / "out", engine="processes")
    assert not (tmp_path / "out" / "logs").exists()       # refused before anything was written


# ------------------------------------------------------------------ item 2: names stable across resumes
def _recorded(folder: Path, sequence: Path) -> None:
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"command": "reconstruct", "parameters": {
        "sequence": str(sequence)}}))


def test_folder_names_keep_the_folders_that_record_their_sequence(tmp_path):
    a, b, c, other = (tmp_path / "seqs" / "alpha", tmp_path / "seqs" / "beta", tmp_path / "seqs" / "gamma",
                      tmp_path / "other" / "alpha")
    out = tmp_path / "out"
    assert folder_names([a, b], out) == (["alpha", "beta"], [])        # no OUT yet: task_names
    _recorded(out / "alpha", a)
    _recorded(out / "beta", b)
    # the list gains a sequence of the same folder name: alpha keeps its folder, the new one is told apart
    assert task_names([a, b, other]) == ["seqs_alpha", "beta", "other_alpha"]
    assert folder_names([a, b, other], out) == (["alpha", "beta", "other_alpha"], [])
    assert folder_names([other, b, a], out) == (["other_alpha", "beta", "alpha"], [])
    # a folder made for a sequence no longer listed is never given to another one, and is named
    names, notes = folder_names([other, c], out)
    assert names == ["other_alpha", "gamma"]
    assert notes == [f"note: {out / n} holds the results of {s}, which the list does not name; left as it is, "
                     "not in the summary" for n, s in (("alpha", a), ("beta", b))]
    # made by a batch of the longer list first: the names it gave are kept when the list shrinks
    out2 = tmp_path / "out2"
    _recorded(out2 / "seqs_alpha", a)
    _recorded(out2 / "other_alpha", other)
    assert folder_names([a, b], out2) == (["seqs_alpha", "beta"], [f"note: {out2 / 'other_alpha'} holds the results "
                                                                  f"of {other}, which the list does not name; left "
                                                                  "as it is, not in the summary"])
    # two folders of one sequence: the one task_names gives is used, the other named
    _recorded(out2 / "alpha", a)
    names, notes = folder_names([a, b], out2)
    assert names == ["alpha", "beta"] and any(f"{out2 / 'seqs_alpha'} holds the results of {a}, which this batch "
                                              f"reports from {out2 / 'alpha'}" in n for n in notes)


@pytest.mark.slow
def test_a_resume_keeps_the_names_of_finished_folders(data, tmp_path):
    out = _resumable(data, tmp_path)
    before = _stamps(out)
    longer = tmp_path / "more.txt"
    longer.write_text(data["list"].read_text() + f"{data['seqs']['other']}\n")
    res = _batch(longer, out, _options(data))
    assert res.returncode == 0, res.stderr
    assert "alpha: skipped, complete in" in res.stdout and "beta: skipped, complete in" in res.stdout
    assert "other_alpha: complete in" in res.stdout and not (out / "seqs_alpha").exists()
    assert {k: v for k, v in _stamps(out).items() if k.startswith(("alpha/", "beta/"))} == \
        {k: v for k, v in before.items() if k.startswith(("alpha/", "beta/"))}        # nothing redone
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["sequence"] for r in rows] == ["alpha", "beta", "other_alpha"]
    assert json.loads((out / "other_alpha" / "config.json").read_text())["parameters"]["sequence"] == \
        str(data["seqs"]["other"])
    # the list without alpha: its folder is named as left out, not silently orphaned
    shorter = tmp_path / "short.txt"
    shorter.write_text(f"{data['seqs']['beta']}\n{data['seqs']['other']}\n")
    res = _batch(shorter, out, _options(data))
    assert res.returncode == 0, res.stderr
    assert f"note: {out / 'alpha'} holds the results of {data['seqs']['alpha']}, which the list does not name" \
        in res.stderr
    assert [r["sequence"] for r in csv.DictReader((out / "summary.csv").open())] == ["beta", "other_alpha"]


# ------------------------------------------------------------------ item 3: damaged folders
def test_damage_names_the_first_missing_empty_or_unreadable_file(tmp_path):
    folder = tmp_path / "run"
    (folder / "none").mkdir(parents=True)
    for name in ("config.json", "metrics.json", "mesh.ply"):
        (folder / name).write_text("{}" if name.endswith(".json") else "ply\n")
    (folder / "none" / "metrics.json").write_text("{}")
    (folder / ".radiomap-files.json").write_text(json.dumps({"files": ["config.json", "mesh.ply", "metrics.json"],
                                                             "folders": ["none"]}))
    (folder / "none" / ".radiomap-files.json").write_text(json.dumps({"files": ["metrics.json"]}))
    assert damage(folder, ["config.json"]) is None
    assert damage(folder, ["summary.txt"]) == "summary.txt is missing"       # named by the command
    (folder / "mesh.ply").unlink()
    assert damage(folder) == "mesh.ply is missing"                           # listed by the run
    (folder / "mesh.ply").write_bytes(b"")
    assert damage(folder) == "mesh.ply is empty"
    (folder / "mesh.ply").write_text("ply\n")
    (folder / "none" / "metrics.json").write_text("{trunc")
    assert damage(folder) == "none/metrics.json does not read as JSON"
    shutil.rmtree(folder / "none")
    assert damage(folder) == "none/ is missing"
    assert recorded_run(folder) is None                                      # config.json holds no parameters


@pytest.mark.slow
def test_a_damaged_folder_is_run_again_naming_the_file(data, tmp_path):
    out = _resumable(data, tmp_path)
    mesh = (out / "alpha" / "mesh.ply").read_bytes()
    (out / "alpha" / "mesh.ply").unlink()
    (out / "beta" / "histogram.json").write_bytes(b"")
    assert all(COMMANDS["reconstruct"].complete(out / n) for n in ("alpha", "beta"))   # finished, but damaged
    res = _batch(data["list"], out, _options(data))
    assert res.returncode == 0, res.stderr
    assert f"alpha: not complete ({out / 'alpha'}/mesh.ply is missing); running it again" in res.stderr
    assert f"beta: not complete ({out / 'beta'}/histogram.json is empty); running it again" in res.stderr
    assert "alpha: complete in" in res.stdout and "beta: complete in" in res.stdout
    assert len((out / "alpha" / "mesh.ply").read_bytes()) == len(mesh)
    json.loads((out / "beta" / "histogram.json").read_text())
    assert {r["status"] for r in csv.DictReader((out / "summary.csv").open())} == {"complete"}


# ------------------------------------------------------------------ item 4: the summary's seconds
@pytest.mark.slow
def test_the_summary_names_which_seconds_it_shows(data, tmp_path):
    out = tmp_path / "cmp"
    one = tmp_path / "one.txt"
    one.write_text(f"{data['seqs']['alpha']}\n")
    res = _batch(one, out, ["-r", str(data["crf"]), "--methods", "none,response", "--views", "0",
                                     "--voxel-size", "0.05", "--depth-max", "6"], command="compare")
    assert res.returncode == 0, res.stderr
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert "seconds" not in rows[0]          # no column that could be taken for compare.csv's seconds
    for row in rows:
        folder = out / row["sequence"]
        table = {r["method"]: r for r in csv.DictReader((folder / "compare.csv").open())}
        metrics = json.loads((folder / row["method"] / "metrics.json").read_text())
        assert float(row["method s"]) == pytest.approx(float(table[row["method"]]["seconds"]), abs=0.006)
        assert float(row["loop s"]) == pytest.approx(metrics["timing"]["seconds"], abs=0.006)
        assert float(row["frames/s"]) == pytest.approx(metrics["timing"]["frames_per_second"], abs=0.006)
    rows = list(csv.DictReader((data["made"] / "summary.csv").open()))
    assert "loop s" in rows[0] and "seconds" not in rows[0]


def test_a_self_calibration_record_compares_file_contents_not_spellings(tmp_path, monkeypatch):
    """A self-calibrate record (what a resumed ``batch self-calibrate`` compares) held its paths as typed and no file
    contents: a response rewritten in place was skipped as complete, the same file spelled from another folder was
    refused, and --no-plots (figures only) refused a resume (review of 2026-11-28). Now the paths are absolute, the
    response's sha256 is recorded and compared, and --no-plots is not compared."""
    from mapping.cli.self_calibrate import command, task_arguments
    from mapping.simulation import sample_sequence
    from radiometry.response import CameraResponse

    seq = sample_sequence("room")
    (tmp_path / "x").mkdir()
    CameraResponse.gamma().save(tmp_path / "x" / "crf.npz")

    def record(cwd, response, *extra):
        monkeypatch.chdir(cwd)
        # the group's help option names: click caches a command's help option at its first context
        with command.make_context("self-calibrate", [str(seq), "-r", response, "-o", str(tmp_path / "out"), *extra],
                                  help_option_names=["-h", "--help"]) as ctx, ctx.scope():
            return task_arguments(ctx)["manifest"]

    first = record(tmp_path / "x", "crf.npz")
    assert first["parameters"]["response"] == str(tmp_path / "x" / "crf.npz")
    assert first["inputs"]["response"]["path"] == str(tmp_path / "x" / "crf.npz")
    assert changed_options(first, record(tmp_path, "x/crf.npz")) == []            # the same file from elsewhere
    assert changed_options(first, record(tmp_path / "x", "crf.npz", "--no-plots")) == []   # figures only
    CameraResponse.gamma(1.8).save(tmp_path / "x" / "crf.npz")                    # rewritten in place
    changed = changed_options(first, record(tmp_path / "x", "crf.npz"))
    assert [name for name, _, _ in changed] == ["response"] and "other contents" in changed[0][2], changed
