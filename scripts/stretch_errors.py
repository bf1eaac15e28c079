"""Where along a synthetic drive each trajectory loses the motion, and how much of the view moves there.

    .venv/bin/python scripts/stretch_errors.py DRIVE EST.txt... [--every 10]

Per stretch of `--every` frame pairs: the mean translation error of each trajectory's frame-to-frame
motion against the drive's `poses.txt` (m per pair), the true distance travelled per pair, and the
share of the image that the drive's motion masks (`motion_2/`, written by `d3lvo synth --traffic`)
mark as moving. A t_rel says how far off a drive ends; this says which stretch put it there, and
whether vehicles filled the view there.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.geometry import relatives
from d3lvo_deploy.poses import read_poses


def translation_errors(gt: np.ndarray, est: np.ndarray) -> np.ndarray:
    """(N-1,) |translation of gt_i^-1 est_i| per pair: how far the estimated step lands from the true one."""
    return np.linalg.norm((np.linalg.inv(relatives(gt)) @ relatives(est))[:, :3, 3], axis=1)


def moving_share(drive: Path, n: int) -> np.ndarray:
    """(n,) share of each frame's pixels marked moving; NaN where the drive has no masks."""
    out = np.full(n, np.nan)
    for i in range(n):
        m = cv2.imread(str(drive / "motion_2" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        if m is not None:
            out[i] = float((m > 0).mean())
    return out


def main(drive: Path, estimates: list[Path], every: int) -> None:
    if not (drive / "poses.txt").is_file():
        sys.exit(f"{drive}: no poses.txt, the ground truth this script scores against")
    gt = read_poses(drive / "poses.txt").poses
    errors = {}
    for e in estimates:
        est = read_poses(e).poses
        if len(est) != len(gt):
            sys.exit(f"{e}: {len(est)} poses, but {drive / 'poses.txt'} has {len(gt)}")
        errors[e.name] = translation_errors(gt, est)
    step = np.linalg.norm(relatives(gt)[:, :3, 3], axis=1)
    share = moving_share(drive, len(gt))
    print("pairs      moving  step m  " + "  ".join(f"{name} m" for name in errors))
    for s in range(0, len(step), every):
        cells = "  ".join(f"{err[s:s + every].mean():{len(name) + 2}.3f}" for name, err in errors.items())
        print(f"{s:3d}-{min(s + every, len(step)) - 1:3d}   {np.nanmean(share[s:s + every]):6.2f}  "
              f"{step[s:s + every].mean():6.3f}  {cells}")
    print("mean" + " " * 22 + "  ".join(f"{err.mean():{len(name) + 2}.3f}" for name, err in errors.items()))


if __name__ == "__main__":
    args = sys.argv[1:]
    every = 10
    if "--every" in args:
        i = args.index("--every")
        value = args[i + 1] if i + 1 < len(args) else ""
        if not value.isdigit() or int(value) < 1:
            sys.exit(f"error: --every takes a number of pairs, 1 or more, not {value!r}")
        every, args = int(value), args[:i] + args[i + 2:]
    if any(a.startswith("--") for a in args):
        sys.exit(f"error: unknown option {next(a for a in args if a.startswith('--'))} (--every N)")
    if len(args) < 2:
        sys.exit(__doc__)
    try:
        main(Path(args[0]), [Path(a) for a in args[1:]], every)
    except D3LVOInputError as e:
        sys.exit(f"error: {e}")
