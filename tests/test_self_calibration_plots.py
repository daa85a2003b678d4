"""The self-calibration's figures (mapping/self_calibration_plots.py) on a made-up result: every file is written,
decodes as an image of the figure's size, and shows the field it was given (the fast tier's test of the module;
tests/test_self_calibration.py::test_cli_on_a_small_simulated_room writes them from a real run)."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np

from mapping.self_calibration_plots import save_figures


def test_save_figures_writes_every_figure(tmp_path):
    h, w = 30, 40
    y, x = np.mgrid[0:h, 0:w]
    r2 = ((x - w / 2) ** 2 + (y - h / 2) ** 2) / (w / 2) ** 2
    lut = np.repeat((1 - 0.4 * r2)[..., None], 3, axis=2).astype(np.float32)
    rng = np.random.default_rng(0)
    result = SimpleNamespace(
        vignetting=SimpleNamespace(evaluate=lambda: lut, stderr=np.full((h, w, 3), 0.01, np.float32)),
        coverage=rng.integers(0, 30, (6, 8)),
        exposures=1 + 0.1 * rng.standard_normal((12, 3)),
        residuals_before=[rng.normal(0, 0.1, 500) for _ in range(3)],
        residuals_after=[rng.normal(0, 0.01, 500) for _ in range(3)])
    files = save_figures(tmp_path, result, np.arange(12))
    assert sorted(files) == ["coverage", "exposures", "residuals", "stderr", "vignetting"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"{name}.png" for name in files)
    for name, path in files.items():
        image = cv2.imread(str(path))
        assert image is not None and image.shape[0] > 150 and image.shape[1] > 200, name
        assert image.std() > 5, f"{name}.png is blank"
    # three panels side by side: the vignetting figure is much wider than tall
    vignetting = cv2.imread(str(files["vignetting"]))
    assert vignetting.shape[1] > 2 * vignetting.shape[0]
