"""The default tracker on the shared real recordings (issue 30's targets): the RealSense office (with its usual
D435 intrinsics) fuses at least 95 % of its frames; the 7-Scenes kitchen's ATE stays where point-to-plane ICP had
it (the lamp shade: tests/test_tracking_real_lampshade.py). The whole table and its command: docs/tracking.md."""

from __future__ import annotations

import pytest
from conftest import shared_path

from mapping.datasets import open_dataset
from mapping.factory import make_backend, make_tracker
from mapping.pipeline import reconstruct

pytestmark = pytest.mark.slow


def run_default(dataset, tracker="auto"):
    """Track and fuse ``dataset`` as ``radiomap reconstruct`` does by default (no files written)."""
    tracker = make_tracker(tracker, depth_max=3.0)
    run = reconstruct(dataset, backend=make_backend("tsdf", voxel_size=0.01, depth_max=3.0), tracker=tracker,
                      progress=False, write_mesh=False)
    return run, tracker


@pytest.mark.slow
def test_the_realsense_office_fuses_95_percent_with_the_default_tracking():
    ds = open_dataset(shared_path("rgbd", "realsense_office_d435"), intrinsics="615,615,320,240")
    run, tracker = run_default(ds)
    assert run.fused >= 0.95 * len(ds), (run.fused, run.skip_reasons(), tracker.stats())


@pytest.mark.slow
def test_the_kitchen_ate_is_not_worse_than_icp_alone():
    """Every third frame of the kitchen at 1 cm voxels: point-to-plane ICP measured 1.090-1.090 cm here (2 runs),
    the default 1.090 cm: it keeps ICP where its system is well-conditioned (the kitchen's condition numbers are
    3.6-5.0); all 100 frames: 1.09 cm with either (docs/tracking.md)."""
    ds = open_dataset(shared_path("rgbd", "redkitchen_7scenes_000-099"), frames=slice(0, 100, 3))
    run, tracker = run_default(ds)
    assert run.fused == len(ds) and run.ate.rmse < 0.0115, (run.ate.rmse, tracker.stats())
