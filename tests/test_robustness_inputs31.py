"""No command writes over one of its own inputs, with or without ``--force`` (issue 31: ``response -o`` naming the
bracket folder's times file and ``vignetting -o`` naming one of the sweep's frames overwrote them; ``correct``
already refused). The refusal comes before anything is written; the inputs stay byte for byte."""

from __future__ import annotations

import os
import shutil

import pytest
from test_robustness import brackets, error_line, paper, room, run, snapshot  # noqa: F401 (fixtures)


@pytest.mark.slow
@pytest.mark.parametrize("name, original", [("times.txt", "times.txt"), ("exposure_0.npz", "exposure_0.png"),
                                            ("times.crf", None)])
@pytest.mark.parametrize("force", [[], ["--force"]], ids=["", "force"])
def test_response_never_writes_over_its_inputs(brackets, name, original, force):  # noqa: F811
    before = snapshot(brackets)
    res = run("response", brackets, "-o", brackets / name, *force)
    if original is None:       # a new name in the input folder that collides with nothing: allowed
        assert res.exit_code == 0, res.output
        return
    if not force and (brackets / name).exists():
        error_line(res, "exists; pass --force")
    else:
        error_line(res, f"is the input {brackets / original}", "--force never replaces an input")
    assert snapshot(brackets) == before


@pytest.mark.slow
def test_vignetting_never_writes_over_its_inputs(paper, tmp_path):  # noqa: F811
    sweep = tmp_path / "sweep"
    shutil.copytree(paper["rgb"], sweep)
    response = tmp_path / "crf.npz"
    shutil.copy(paper["response"], response)
    frame = sorted(sweep.iterdir())[3]
    before = snapshot(tmp_path)
    error_line(run("vignetting", sweep, "-r", response, "-o", frame, "--force"), f"is the input {frame}")
    error_line(run("vignetting", sweep, "-r", response, "-o", response, "--force"), f"is the input {response}")
    os.symlink(sweep, tmp_path / "link")     # the same frame through a symbolic link to the folder
    error_line(run("vignetting", tmp_path / "link", "-r", response, "-o", frame.with_suffix(".png"), "--force"),
               "is the input")
    (tmp_path / "link").unlink()
    assert snapshot(tmp_path) == before


@pytest.mark.slow
@pytest.mark.parametrize("command", ["reconstruct", "self-calibrate"])
def test_a_results_folder_is_never_its_sequence(room, tmp_path, command):  # noqa: F811
    seq = tmp_path / "seq"
    shutil.copytree(room, seq)
    before = snapshot(seq)
    error_line(run(command, seq, "-o", seq, "--force", "--poses", "gt", "--no-progress"),
               "is the input sequence", "choose another output folder")
    assert snapshot(seq) == before


def test_compare_into_its_sequence_is_refused(room, tmp_path):  # noqa: F811
    seq = tmp_path / "seq"
    shutil.copytree(room, seq)
    before = snapshot(seq)
    error_line(run("compare", seq, "-r", seq / "truth" / "response.npz", "--methods", "none", "-o", seq, "--force"),
               "is the input sequence")
    assert snapshot(seq) == before


def test_ctrl_c_while_the_command_is_still_importing_is_one_line():
    """The entry point catches a Ctrl-C that arrives while the heavy libraries load (simulated: the import of
    mapping.cli raises KeyboardInterrupt, as a SIGINT at that moment does); ``import mapping`` itself loads no NumPy."""
    import subprocess
    import sys

    script = ("import sys\n"
              "class Stop:\n"
              "    def find_spec(self, name, path=None, target=None):\n"
              "        if name == 'mapping.cli':\n"
              "            raise KeyboardInterrupt\n"
              "sys.meta_path.insert(0, Stop())\n"
              "import mapping\n"
              "assert 'numpy' not in sys.modules, 'import mapping loaded NumPy'\n"
              "from mapping._entry import main\n"
              "sys.exit(main())\n")
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert res.returncode == 130 and res.stderr == "radiomap: interrupted\n", (res.returncode, res.stderr)
