"""The default tracker on the shared RealSense lamp shade (issue 30's target): with no options (its
camera_intrinsic.json read) at least 95 % of its 120 frames are fused. (A file of its own: each real sequence costs
~20-25 s.)"""

from __future__ import annotations

import pytest
from conftest import shared_path

from mapping.datasets import open_dataset
from mapping.factory import make_backend, make_tracker
from mapping.pipeline import reconstruct

pytestmark = pytest.mark.slow


@pytest.mark.slow
def test_the_lampshade_fuses_95_percent_with_the_default_tracking():
    ds = open_dataset(shared_path("rgbd", "realsense_lampshade"))
    tracker = make_tracker(depth_max=3.0)   # the default: auto
    run = reconstruct(ds, backend=make_backend("tsdf", voxel_size=0.01, depth_max=3.0), tracker=tracker,
                      progress=False, write_mesh=False)
    assert run.fused >= 0.95 * len(ds), (run.fused, run.skip_reasons(), tracker.stats())
