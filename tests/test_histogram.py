"""Colour-disagreement histogram: exact statistics, files, plots; corrected vs raw fusion under vignetting."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mapping.histogram import BINS, DisagreementHistogram
from radiometry.errors import CalibrationFileError


def test_l1_over_channels_rounded_to_whole_levels():
    h = DisagreementHistogram()
    n = h.add(np.array([[10, 20, 30], [0, 0, 0], [100.2, 50, 7]], np.float32),
              np.array([[11, 18, 35], [255, 255, 255], [100, 50.1, 7.1]], np.float32))
    assert n == 3 and h.total == 3
    assert h.counts[8] == 1 and h.counts[765] == 1 and h.counts[0] == 1   # 1+2+5, 3x255, 0.4 rounds to 0
    np.testing.assert_allclose(DisagreementHistogram.distances(np.zeros((1, 3)), np.full((1, 3), 0.5)), [1.5])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_statistics_are_exact(seed):
    rng = np.random.default_rng(seed)
    values = rng.integers(0, 766, size=rng.integers(1, 5000))
    h = DisagreementHistogram()
    h.add_distances(values.astype(np.float32))
    s = h.stats()
    assert s["count"] == values.size
    assert s["mean"] == pytest.approx(values.mean(), rel=1e-12)
    assert s["median"] == np.percentile(values, 50, method="inverted_cdf")
    assert s["p90"] == np.percentile(values, 90, method="inverted_cdf")
    assert s["std"] == pytest.approx(values.std(), rel=1e-9)


def test_known_small_cases():
    h = DisagreementHistogram()
    h.add_distances(np.array([1, 2, 3, 4], np.float32))
    assert (h.mean(), h.median(), h.percentile(0.9), h.percentile(1.0)) == (2.5, 2.0, 4.0, 4.0)
    h.add_distances(np.array([np.nan, np.inf, -3.0, 1e6], np.float32))   # NaN/inf skipped, the rest clipped
    assert h.total == 6 and h.counts[0] == 1 and h.counts[765] == 1
    empty = DisagreementHistogram()
    assert empty.total == 0 and np.isnan(empty.mean()) and np.isnan(empty.median())
    with pytest.raises(ValueError, match="q must be"):
        h.percentile(0)


def test_merge_and_add():
    a, b = DisagreementHistogram(label="a"), DisagreementHistogram()
    a.add_distances(np.array([1, 1, 5], np.float32))
    b.add_distances(np.array([5, 9], np.float32))
    c = a + b
    assert c.total == 5 and a.total == 3 and c.label == "a"
    a.merge(b)
    np.testing.assert_array_equal(a.counts, c.counts)
    with pytest.raises(TypeError, match="DisagreementHistogram"):
        a.merge(np.zeros(BINS))
    with pytest.raises(ValueError, match="766 bins"):
        DisagreementHistogram(np.zeros(10))
    with pytest.raises(ValueError, match="same shape"):
        a.add(np.zeros((2, 3)), np.zeros((3, 3)))


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_save_load_round_trip(tmp_path, suffix):
    h = DisagreementHistogram(label="LUT vignetting")
    h.add_distances(np.random.default_rng(4).gamma(2.0, 10.0, 10000).astype(np.float32))
    path = h.save(tmp_path / f"hist{suffix}")
    back = DisagreementHistogram.load(path)
    np.testing.assert_array_equal(back.counts, h.counts)
    assert back.label == "LUT vignetting" and back.stats() == h.stats()
    if suffix == ".json":
        doc = json.loads(path.read_text())
        assert doc["stats"]["median"] == h.median() and doc["bin_width"] == 1


def test_malformed_files(tmp_path):
    bad = tmp_path / "h.json"
    bad.write_text('{"kind": "disagreement-histogram", "counts": [1, 2]}')
    with pytest.raises(CalibrationFileError, match="766 bins"):
        DisagreementHistogram.load(bad)
    bad.write_text("{not json")
    with pytest.raises(CalibrationFileError, match=r"h\.json:1: invalid JSON"):
        DisagreementHistogram.load(bad)
    with pytest.raises(CalibrationFileError, match="no such histogram"):
        DisagreementHistogram.load(tmp_path / "missing.json")
    with pytest.raises(ValueError, match=".json or .npz"):
        DisagreementHistogram().save(tmp_path / "h.csv")
    # an empty histogram's statistics are NaN: written as JSON null
    DisagreementHistogram().save(tmp_path / "empty.json")
    assert json.loads((tmp_path / "empty.json").read_text())["stats"]["mean"] is None


def test_plot_histograms(tmp_path):
    from matplotlib.figure import Figure

    from mapping.plots import plot_histograms, save_histogram_figure

    rng = np.random.default_rng(5)
    raw, corrected = DisagreementHistogram(), DisagreementHistogram()
    raw.add_distances(rng.gamma(2.0, 15.0, 5000).astype(np.float32))
    corrected.add_distances(rng.gamma(2.0, 5.0, 5000).astype(np.float32))
    ax = Figure().subplots()
    assert plot_histograms(ax, {"none": raw, "LUT": corrected.counts}, log_y=True) is ax
    assert ax.get_yscale() == "log" and len(ax.get_legend().get_texts()) == 2
    assert "mean 30" in ax.get_legend().get_texts()[0].get_text()
    steps = [line for line in ax.get_lines() if len(line.get_xdata()) == BINS]
    assert len(steps) == 2 and steps[0].get_ydata().sum() == pytest.approx(1.0)     # normalised
    save_histogram_figure(tmp_path / "h.png", {"none": raw})
    assert (tmp_path / "h.png").stat().st_size > 5000
    with pytest.raises(ValueError, match="at least one"):
        plot_histograms(ax, {})


def test_correction_lowers_disagreement_under_strong_vignetting():
    """A camera with strong vignetting (V = 0.45 in the corners) and a gamma response sweeps a textured box
    room: fused as raw intensities, every surface changes colour as it crosses the image; fused as irradiance
    f^-1(I)/V it does not, up to 8-bit quantisation."""
    from mapping.colour import IrradianceColour, RawIntensity
    from box_room import box_room_sequence, radial_vignetting
    from mapping.factory import make_backend
    from mapping.pipeline import reconstruct
    from radiometry.response import CameraResponse

    response = CameraResponse.gamma(2.2)
    V = radial_vignetting(120, 160, 0.55)
    ds, _ = box_room_sequence(n_frames=10, width=160, height=120, step=0.03, turn_deg=1.5, response=response,
                              vignetting=V, exposure=0.9)
    runs = {}
    for name, model in (("none", RawIntensity()), ("lut", IrradianceColour(response, V, reference_exposure=0.9))):
        runs[name] = reconstruct(ds, colour_model=model, backend=make_backend("tsdf", voxel_size=0.02, depth_max=5.0),
                                 poses="gt", progress=False).histogram
    raw, corrected = runs["none"].stats(), runs["lut"].stats()
    assert raw["count"] > 50000 and corrected["count"] == pytest.approx(raw["count"], rel=0.02)
    assert corrected["mean"] < 0.35 * raw["mean"]
    assert corrected["p90"] < raw["p90"]
    assert raw["mean"] > 8.0 and corrected["mean"] < 4.0     # measured: 14.9 and 1.5 (p90 30 and 3)


def test_a_binary_file_is_not_a_histogram(tmp_path):
    """A .npy (or any binary file) under another name than .npz is a one-line error, not a UnicodeDecodeError."""
    bad = tmp_path / "h.npy"
    np.save(bad, np.arange(766, dtype=np.float32) * 1000.0)
    with pytest.raises(CalibrationFileError, match=r"h\.npy: a binary file, not a histogram"):
        DisagreementHistogram.load(bad)
