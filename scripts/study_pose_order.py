#!/usr/bin/env python
"""Study: the depth agreement of mapping.pose_convention under the four readings of a TUM file's poses (as given,
inverted, quaternions read scalar-first, scalar-first and inverted) on the real 7-Scenes kitchen (its ground
truth written as TUM rows: correct, written ``qw qx qy qz``, inverted, both), for several frame selections. The
files are built from the pose matrices with scipy (an independent writer), not with the code under test.

    python scripts/study_pose_order.py                      # kitchen 0:100, 0:100:5, 50:70, 0:20 (about 20 s)
    python scripts/study_pose_order.py --frames 0:10 --sequence PATH
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

KITCHEN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "rgbd" / "redkitchen_7scenes_000-099"


def written_scalar_first(pose: np.ndarray) -> np.ndarray:
    """The pose a TUM reader gets from ``pose`` written ``qw qx qy qz`` (scipy's scalar-first quaternion)."""
    out = np.array(pose, dtype=np.float64)
    out[:3, :3] = Rotation.from_quat(Rotation.from_matrix(pose[:3, :3]).as_quat(scalar_first=True)).as_matrix()
    return out


def main() -> None:
    from types import SimpleNamespace

    from mapping.datasets import open_dataset
    from mapping.pose_convention import check_convention

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", type=Path, default=KITCHEN)
    ap.add_argument("--frames", nargs="*", default=["0:100", "0:100:5", "50:70", "0:20"])
    args = ap.parse_args()
    print("frames     file                    as given  inverted  scalar-first  sf inverted  verdict")
    for spec in args.frames:
        ds = open_dataset(args.sequence, frames=slice(*[int(x) if x else None for x in spec.split(":")]))
        frames = [ds[i] for i in range(len(ds))]
        files = {"correct": lambda T: T, "written qw qx qy qz": written_scalar_first,
                 "inverted": np.linalg.inv, "qw qx qy qz, inverted": lambda T: written_scalar_first(np.linalg.inv(T))}
        for name, write in files.items():
            seq = [SimpleNamespace(depth=f.depth, K=f.K, pose=write(np.asarray(f.pose, np.float64))) for f in frames]
            c = check_convention(seq, quaternions=True)
            print(f"{spec:<10} {name:<23} {c.given:8.2f}  {c.inverted:8.2f}  {c.scalar_first:12.2f}  "
                  f"{c.scalar_first_inverted:11.2f}  {c.verdict}")


if __name__ == "__main__":
    main()
