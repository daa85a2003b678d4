"""Self-calibration on a camera built independently of radiomap (tests/selfcal_camera.py; issue 29): the hand-held
scan is recovered, the steady pan is flagged as ambiguous and its stated error covers the truth. The full-size
study (640x480, 80 frames) is scripts/study_self_calibration.py (docs/self_calibration.md)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))


@pytest.fixture(scope="module")
def study():
    from study_self_calibration import study as run

    return run


@pytest.mark.slow
def test_hand_held_scan_is_recovered_and_validated(study):
    row = study("scan", frames=40, size=320, known=False)
    assert not row["ambiguity"] and row["warnings"] == [], row["warnings"]
    assert max(row["v_error_levels"]) <= 1.0, row
    assert max(row["exposure_error_median_pct"]) <= 1.0, row
    assert row["validation"]["v_helps"] and np.mean(row["validation"]["l1_with_v"]) < 0.5 * np.mean(
        row["validation"]["l1_without_v"])


@pytest.mark.slow
def test_steady_pan_is_flagged_and_its_error_covers_the_truth(study):
    row = study("pan", frames=40, size=320, known=False)
    assert row["ambiguity"] and any("cannot pin" in w for w in row["warnings"]), row
    assert max(row["v_error_levels"]) <= 1.5 or min(row["within_2_stderr_pct"]) >= 80.0, row


@pytest.mark.slow
def test_steady_pan_with_the_true_exposures_given_is_recovered(study):
    """Known exposures take the exposure drift out of the pan's ambiguity: the left-right tilt is pinned (its
    visibility ~75 %), the up-down one is seen only through the perspective drift of points near the corners
    (~0.2 %), where V's vertical structure is held near the plausible member. Measured at 640x480, 80 frames, seeds
    0-2: 1.01-1.19 levels (the target of issue 29 is 1.5; at 320x240 and 40 frames 1.37-1.47, too near it to test
    there)."""
    row = study("pan", frames=80, size=640, known=True)
    assert max(row["exposure_error_median_pct"]) == 0.0, row      # the given exposures are held
    assert row["tilt_visibility"][0] > 0.5 and row["tilt_visibility"][1] < 0.004, row
    assert max(row["v_error_levels"]) <= 1.5, row
    assert min(row["within_2_stderr_pct"]) >= 80.0, row
    assert not row["ambiguity"] and any(line.startswith("note: V's up-down profile is seen weakly")
                                        for line in row["lines"]), row
