"""Fuzzing of the RGB-D dataset readers: TUM lists, trajectories and whole folders, 7-Scenes poses, Redwood
.log trajectories, camera intrinsics (text and JSON) and simulator manifests.

Random and mutated inputs must raise only radiomap's own errors; see ``fuzz_helpers`` for the method.
"""

from __future__ import annotations

import json
import math
import random
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzz_helpers import (
    SEEDS, fuzz, grammar_text, hostile_json, mutate_text, only_own_errors, put, random_input)
from fuzz_helpers import fuzz_watchdog, workdir  # noqa: F401 (pytest fixtures: the watchdog, a scratch folder)


# ==================================================================================================
# TUM lists and trajectories, 7-Scenes poses, Redwood .log, camera intrinsics, simulator manifests
# ==================================================================================================
TUM_LIST = "# color images\n# timestamp filename\n1305031102.175304 rgb/1305031102.175304.png\n" \
           "1305031102.211214 rgb/1305031102.211214.png\n1305031102.243211 rgb/1305031102.243211.png\n"
TUM_TRAJ = "# ground truth trajectory\n# timestamp tx ty tz qx qy qz qw\n" \
           "1305031102.1758 1.3405 0.6266 1.6575 0.6574 0.6126 -0.2949 -0.3248\n" \
           "1305031102.2058 1.3303 0.6256 1.6464 0.6579 0.6161 -0.2932 -0.3189\n" \
           "1305031102.2358 1.3160 0.6254 1.6302 0.6583 0.6200 -0.2907 -0.3136\n"
POSE = "0.99 0.01 -0.1 0.1\n-0.01 0.99 0.0 -0.2\n0.1 0.0 0.99 1.5\n0 0 0 1\n"
LOG = "0 0 3\n1 0 0 0.5\n0 1 0 0\n0 0 1 1\n0 0 0 1\n1 1 3\n1 0 0 0.6\n0 1 0 0\n0 0 1 1\n0 0 0 1\n"
INTRINSICS_TXT = "525.0 0 319.5\n0 525.0 239.5\n0 0 1\n"
CAMERA_JSON = json.dumps({"width": 640, "height": 480,
                          "intrinsic_matrix": [525.0, 0, 0, 0, 525.0, 0, 319.5, 239.5, 1]})


def text_input(rng: random.Random, seed_text: str, columns: list[int], max_rows: int = 12) -> bytes | str:
    which = rng.random()
    if which < 0.6:
        return mutate_text(seed_text, rng)
    if which < 0.85:
        return grammar_text(rng, columns, max_rows=max_rows)
    return random_input(rng, text=True)


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_tum_list(workdir, seed):
    from mapping.datasets._common import read_stamped_list

    data = text_input(random.Random(seed), TUM_LIST, [2])
    rows = only_own_errors(read_stamped_list, put(workdir, "rgb.txt", data))
    if rows is not None:
        assert all(math.isfinite(t) and name for t, name, _ in rows)


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_tum_trajectory(workdir, seed):
    from mapping.metrics import read_tum_trajectory

    data = text_input(random.Random(seed), TUM_TRAJ, [8])
    result = only_own_errors(read_tum_trajectory, put(workdir, "groundtruth.txt", data))
    if result is not None:
        stamps, poses = result
        assert len(stamps) == len(poses) and np.all(np.isfinite(poses)) and np.all(np.isfinite(stamps))


@pytest.fixture(scope="module")
def tum_folder(workdir) -> Path:
    root = workdir / "rgbd_dataset_freiburg1_fuzz"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for stamp in ("1305031102.175304", "1305031102.211214", "1305031102.243211"):
        cv2.imwrite(str(root / "rgb" / f"{stamp}.png"), np.full((48, 64, 3), 128, np.uint8))
        cv2.imwrite(str(root / "depth" / f"{stamp}.png"), np.full((48, 64), 10000, np.uint16))
    return root


TUM_FILES = {"rgb.txt": TUM_LIST, "depth.txt": TUM_LIST.replace("rgb/", "depth/"), "groundtruth.txt": TUM_TRAJ,
             "intrinsics.txt": "60.0 60.0 31.5 23.5\n"}


@pytest.mark.slow
@fuzz(2000)
@given(seed=SEEDS, which=st.sampled_from(sorted(TUM_FILES)))
def test_tum_folder_with_one_mutated_file(tum_folder, seed, which):
    """A whole TUM folder (three real frames) with one text file mutated: open it, read every frame and
    the ground truth, as 'radiomap reconstruct' does."""
    from mapping.datasets.tum import TUMDataset

    rng = random.Random(seed)
    for name, text in TUM_FILES.items():
        columns = {"groundtruth.txt": [8], "intrinsics.txt": [3, 4]}.get(name, [2])
        put(tum_folder, name, text_input(rng, text, columns, max_rows=5) if name == which else text)

    def open_and_read():
        ds = TUMDataset(tum_folder)
        frames = [ds[i] for i in range(len(ds))]
        gt = ds.ground_truth()
        assert gt is None or np.all(np.isfinite(gt[1]))
        return frames

    only_own_errors(open_and_read)


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_sevenscenes_pose(workdir, seed):
    from mapping.datasets._common import read_pose_matrix_file

    data = text_input(random.Random(seed), POSE, [4], max_rows=5)
    pose = only_own_errors(read_pose_matrix_file, put(workdir, "frame-000000.pose.txt", data))
    if pose is not None:
        assert pose.shape == (4, 4) and np.all(np.isfinite(pose))


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_redwood_log(workdir, seed):
    from mapping.datasets.redwood import read_log_trajectory

    data = text_input(random.Random(seed), LOG, [3, 4, 4, 4, 4], max_rows=15)
    poses = only_own_errors(read_log_trajectory, put(workdir, "trajectory.log", data))
    if poses is not None:
        assert all(p.shape == (4, 4) and np.all(np.isfinite(p)) for p in poses.values())


def camera_json(rng: random.Random) -> str:
    """An Open3D camera JSON (or the K / fx,fy,cx,cy forms) with hostile values, lengths and types."""
    doc = json.loads(CAMERA_JSON)
    key = rng.choice(["intrinsic_matrix", "K", "fx"])
    if key != "intrinsic_matrix":
        doc.pop("intrinsic_matrix")
    if key == "fx":
        doc.update(fx=525.0, fy=525.0, cx=319.5, cy=239.5)
        doc[rng.choice(["fx", "fy", "cx", "cy"])] = hostile_json(rng)
    else:
        flat = [525.0, 0, 319.5, 0, 525.0, 239.5, 0, 0, 1] if key == "K" else list(doc["intrinsic_matrix"])
        op = rng.choice(["element", "length", "whole"])
        if op == "element":
            flat[rng.randrange(9)] = hostile_json(rng)
            doc[key] = flat
        elif op == "length":
            doc[key] = flat[:rng.randint(0, 8)] + flat[:rng.randint(0, 3)]
        else:
            doc[key] = hostile_json(rng)
    if rng.random() < 0.05:
        return "[" * 100_000
    return json.dumps(doc, allow_nan=True)


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_camera_intrinsics_json(workdir, seed):
    from mapping.datasets._common import read_intrinsics_file

    rng = random.Random(seed)
    data = camera_json(rng) if rng.random() < 0.6 else text_input(rng, CAMERA_JSON, [1])
    K = only_own_errors(read_intrinsics_file, put(workdir, "camera_primesense.json", data))
    if K is not None:
        assert K.shape == (3, 3) and np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0


@pytest.mark.slow
@fuzz(3000)
@given(seed=SEEDS)
def test_camera_intrinsics_txt(workdir, seed):
    from mapping.datasets._common import read_intrinsics_file

    rng = random.Random(seed)
    data = text_input(rng, rng.choice([INTRINSICS_TXT, "525 525 319.5 239.5\n"]), [3, 4], max_rows=4)
    K = only_own_errors(read_intrinsics_file, put(workdir, "camera-intrinsics.txt", data))
    if K is not None:
        assert K.shape == (3, 3) and np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0


MANIFEST = json.dumps({"format": "radiomap-sim", "version": 1, "kind": "room", "width": 64, "height": 48,
                       "K": [[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]], "depth_scale": 5000.0, "n_frames": 3})


@pytest.mark.slow
@fuzz(2000)
@given(seed=SEEDS)
def test_simulated_manifest(tum_folder, seed):
    """A simulator manifest beside a valid TUM folder: SimulatedDataset opens it or fails cleanly."""
    from mapping.datasets.simulated import MANIFEST as NAME, SimulatedDataset

    rng = random.Random(seed)
    doc = json.loads(MANIFEST)
    for _ in range(rng.randint(1, 3)):
        doc[rng.choice(sorted(doc))] = hostile_json(rng)
    data = json.dumps(doc, allow_nan=True) if rng.random() < 0.7 else mutate_text(MANIFEST, rng)
    for name, text in TUM_FILES.items():
        put(tum_folder, name, text)
    put(tum_folder, NAME, data)
    try:
        only_own_errors(lambda: SimulatedDataset(tum_folder)[0])
    finally:
        (tum_folder / NAME).unlink()
