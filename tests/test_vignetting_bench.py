"""Smoke test of ``scripts/bench_vignetting.py`` on a tiny case that needs no shared data (asymmetric preset,
gamma 2.2): it runs and its rows hold finite, plausible errors."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest


@pytest.mark.slow
def test_bench_vignetting_rows(capsys):
    path = Path(__file__).resolve().parents[1] / "scripts" / "bench_vignetting.py"
    spec = importlib.util.spec_from_file_location("radiomap_script_bench_vignetting", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    rows = script.run(["asymmetric"], ["gamma-2.2"], ["debevec"], "2x", 40, (160, 120))
    assert [r["response"] for r in rows] == ["truth", "debevec"]
    for row in rows:
        rms = np.array(row["LUT RMS [levels] R/G/B"].split("/"), dtype=float)
        budget = np.array(row["budget R/G/B"].split("/"), dtype=float)
        assert np.all(np.isfinite(rms)) and np.all(rms > 0) and np.all(rms < 1.0), row
        assert np.all(budget > 0) and row["<= 0.5"] in ("yes", "no")
    assert rows[0]["response part R/G/B"] == "0.00/0.00/0.00"
    assert "debevec" in capsys.readouterr().out
