"""How well do the images tell a recorded exposure list's alignment? (mapping/exposure_alignment.py)

Real frames of ../shared/data (none of them has recorded exposures) with exposures imposed on purpose: each frame's
irradiance ``f^-1(I)`` (a gamma 2.2 response) scaled by ``k_i`` (a random walk of log steps of sd 0.12 kept within
[1/3, 3], or a slow swing ``0.4 sin(2 pi i / 30)``), and written back through the response, on top of the
camera's own auto exposure (not known, a noise the check must live with). Last, radiomap's simulated room (strong
vignetting the check is not given, which biases the images' ratios as the camera pans; its own auto exposure is
in the list). The list is written with the frames' own timestamps: correct, shifted by +-1 and +-2
rows, and with its clock one frame period + 0.01 s late (each frame then matches the row of the frame before,
within the 0.02 s window). Prints the disagreement (log units) by shift and the verdict.

    .venv/bin/python scripts/study_exposure_alignment.py [--frames 60]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rgbd"
SEQUENCES = {"kitchen": DATA / "redkitchen_7scenes_000-099", "office": DATA / "realsense_office_d435",
             "lampshade": DATA / "realsense_lampshade"}


def impose(dataset, n: int, seed: int, response, profile: str = "walk"):
    """An in-memory copy of the first ``n`` frames with exposures ``k`` imposed; ``(dataset, k, stamps)``.
    ``walk``: log steps of sd 0.12; ``smooth``: ``0.4 sin(2 pi i / 30)`` (auto exposure's slow swing)."""
    from mapping.datasets.base import RGBDFrame
    from mapping.datasets.in_memory import ArrayDataset

    rng = np.random.default_rng(seed)
    if profile == "walk":
        logk = np.clip(np.cumsum(rng.normal(0, 0.12, n)), -1.1, 1.1)
    else:
        logk = 0.4 * np.sin(2 * np.pi * (np.arange(n) + 7 * seed) / 30)
    k = np.exp(logk - logk[0])
    frames = []
    for i in range(n):
        f = dataset[i]
        e = response.inverse(np.asarray(f.rgb)) * k[i]
        rgb = response.forward(e, dtype=np.uint8)
        frames.append(RGBDFrame(index=f.index, timestamp=f.timestamp, rgb=rgb, depth=f.depth, K=f.K))
    return ArrayDataset(frames), k, np.array([f.timestamp for f in frames])


def simulated_room(out: Path, n: int):
    """radiomap's simulated room (160x120, the 'asymmetric' camera: strong, off-centre vignetting, its own auto
    exposure): ``(folder, response, truth rows)``."""
    from mapping.simulation.sequences import simulate_room
    from mapping.simulation.trajectory import HandheldMotion
    from radiometry.formats import load_response
    from radiometry.simulation.camera import CameraSpec

    simulate_room(out, camera=CameraSpec.preset("asymmetric", width=160, height=120), seed=1, n_frames=n,
                  width=160, height=120, motion=HandheldMotion(speed=3.0), progress=False)
    truth = np.loadtxt(out / "truth" / "exposures.txt")
    return out, load_response(out / "truth" / "response.npz"), truth


def write_list(path: Path, stamps: np.ndarray, k: np.ndarray, shift: int = 0, offset: float = 0.0) -> Path:
    """Rows ``(stamp_i + offset, k_{i-shift})``: shift > 0 lists each exposure ``shift`` rows late."""
    rows = [(stamps[i] + offset, k[i - shift]) for i in range(len(k)) if 0 <= i - shift < len(k)]
    path.write_text("".join(f"{t:.6f} {v:.6f}\n" for t, v in rows))
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--seeds", type=int, default=2)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from mapping.datasets import open_dataset
    from mapping.exposure_alignment import check_alignment
    from mapping.exposure_files import match_exposure_file
    from radiometry.response import CameraResponse

    gamma = CameraResponse.gamma(2.2)
    print("| sequence | exposures | list | pairs | d1(-2) | d1(-1) | d1(0) | d1(+1) | d1(+2) | d4(-1) | d4(0) | "
          "d4(+1) | verdict |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name, folder in [*SEQUENCES.items(), ("room, V not given", None)]:
            response, truth = gamma, None
            if folder is None:      # a simulated camera with strong vignetting that the check is not given
                folder, response, truth = simulated_room(Path(tmp) / "room", args.frames)
            if not folder.is_dir():
                print(f"{name}: {folder} absent, skipped")
                continue
            base = open_dataset(folder)
            n = min(args.frames, len(base))
            for seed, profile in [(s, p) for p in ("walk", "smooth") for s in range(args.seeds)]:
                ds, k, stamps = impose(base, n, seed, response, profile)
                if truth is not None:
                    k = k * truth[:n, 1]
                period = float(np.median(np.diff(stamps)))
                cases = {"correct": {}, "shift +1": {"shift": 1}, "shift -1": {"shift": -1},
                         "shift +2": {"shift": 2}, "clock +1.3 frames": {"offset": period + 0.01},
                         "constant": None}
                for label, how in cases.items():
                    path = Path(tmp) / "k.txt"
                    if how is None:
                        write_list(path, stamps, np.ones_like(k))
                    else:
                        write_list(path, stamps, k, **how)
                    table = match_exposure_file(ds, path)
                    check = check_alignment(ds, table, response)
                    d = {check.baseline: check.disagreement, **check.others}
                    d1, d4 = d.get(1, {}), d.get(4, {})
                    cells = " | ".join(f"{d1[s]:.3f}" if s in d1 else "-" for s in (-2, -1, 0, 1, 2))
                    cells += " | " + " | ".join(f"{d4[s]:.3f}" if s in d4 else "-" for s in (-1, 0, 1))
                    extra = f" ({check.shift:+d})" if check.shift else ""
                    print(f"| {name} | {profile} {seed} | {label} | {check.pairs} | {cells} | {check.verdict}{extra} |",
                          flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
