"""A KITTI-format drive with frames dropped, as a sensor that misses some: what the runtime does
when the gap between two frames is twice the usual.

    .venv/bin/python scripts/drop_frames.py DRIVE OUT [--every N] [--phase K] [--uniform-times]

Writes OUT with every N-th frame of DRIVE (default 10, from frame K, default 5) left out: its images
and scans linked, not copied, `times.txt` and `poses.txt` of the frames kept, and its calibration.
With `--uniform-times` the kept frames get times 0.1 s apart instead of their own, as a recording
that numbers its frames without saying when they were taken: each pair then starts from the last
pair's motion whatever the gap (docs/evaluation.md, "Dropped frames").
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

import numpy as np

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.sequence import KittiSequence


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("drive", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--phase", type=int, default=5)
    ap.add_argument("--uniform-times", action="store_true")
    a = ap.parse_args()
    if a.every < 2:
        sys.exit("error: --every must be 2 or more")
    seq = KittiSequence.open(a.drive)
    if seq.ground_truth is None:
        raise D3LVOInputError(a.drive, "has no poses.txt")
    if a.out.exists():
        raise D3LVOInputError(a.out, "exists already; name a new folder")
    keep = [i for i in range(len(seq)) if i % a.every != a.phase % a.every]
    for sub in ("image_2", "velodyne"):
        (a.out / sub).mkdir(parents=True)
        for j, i in enumerate(keep):
            src = (seq.image_path(i) if sub == "image_2" else seq.scan_path(i)).resolve()
            os.symlink(src, a.out / sub / f"{j:06d}{src.suffix}")
    times = np.arange(len(keep)) * 0.1 if a.uniform_times else seq.times[keep]
    np.savetxt(a.out / "times.txt", times, fmt="%.6e")
    np.savetxt(a.out / "poses.txt", seq.ground_truth.poses[keep][:, :3, :].reshape(len(keep), 12))
    shutil.copyfile(a.drive / "calib.txt", a.out / "calib.txt")
    print(f"{a.out}: {len(keep)} of {len(seq)} frames (every {a.every}-th from {a.phase} left out), "
          f"{'times 0.1 s apart' if a.uniform_times else 'their own times'}")


if __name__ == "__main__":
    try:
        main()
    except D3LVOInputError as e:
        sys.exit(f"error: {e}")
