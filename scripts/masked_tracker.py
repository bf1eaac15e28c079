"""The classical tracker with the points an oracle knows to be untrustworthy removed.

    .venv/bin/python scripts/masked_tracker.py DRIVE OUT.txt [--shadows] [--max-accel A]

Runs `d3lvo run DRIVE --method direct` (the bundled model's classical mode) but drops, before each
pair, frame t-1's LiDAR points whose pixel the drive's `motion_2/` marks (they lie on a moving
vehicle) and, with `--shadows`, also those `shadow_2/` marks (a moving vehicle's shadow changes
their shading by frame t). What a perfect confidence, used as a gate, would give: the bound the
learned one is measured against, and whether a kind of pixel is worth teaching it
(docs/model-card.md). Drives rendered with `d3lvo synth --traffic` only. `--max-accel` as `d3lvo
run`'s (the motion guard, off by default).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.direct import DirectConfig, DirectOdometry, TrackedFrame
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.manifest import load_manifest
from d3lvo_deploy.motion_guard import MotionGuard
from d3lvo_deploy.points import project
from d3lvo_deploy.poses import write_poses
from d3lvo_deploy.results import make_output_folder
from d3lvo_deploy.sequence import KittiSequence


def untrusted(drive: Path, i: int, shadows: bool) -> np.ndarray:
    mask = cv2.imread(str(drive / "motion_2" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        sys.exit(f"{drive}/motion_2/{i:06d}.png: no motion mask (render the drive with --traffic)")
    if not shadows:
        return mask > 0
    path = drive / "shadow_2" / f"{i:06d}.png"
    if not path.is_file():  # the last frame has none: it is never frame t-1
        if (drive / "flow_2" / path.name).is_file():
            sys.exit(f"{path}: missing (render the drive again with d3lvo synth, which adds shadow_2/)")
        return mask > 0
    return (mask > 0) | (cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0)


def without(f: TrackedFrame, bad: np.ndarray) -> TrackedFrame:
    """The frame with its points on the pixels `bad` (H,W) marks dropped (nearest pixel)."""
    uv = np.rint(project(f.points, f.levels[0].K)[0]).astype(int)
    uv = np.clip(uv, 0, [bad.shape[1] - 1, bad.shape[0] - 1])
    return TrackedFrame(f.levels, f.points[~bad[uv[:, 1], uv[:, 0]]], f.depth)


def main(drive: Path, out: Path, shadows: bool, guard: MotionGuard) -> None:
    seq = KittiSequence.open(drive)
    odo = DirectOdometry(seq.calib, DirectConfig.of_model(load_manifest(bundled_model_dir())["model_config"]), guard)
    frame = odo._frame

    def masked(image: np.ndarray, points: np.ndarray) -> TrackedFrame:
        return without(frame(image, points), untrusted(drive, odo.frames, shadows))

    odo._frame = masked
    write_poses(out, np.array([odo.step(seq.image(i), seq.scan(i), float(seq.times[i])) for i in range(len(seq))]))
    print(f"{len(seq)} poses in {out}")


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--shadows"]
    guard = MotionGuard()
    if "--max-accel" in args:
        k = args.index("--max-accel")
        try:
            guard = MotionGuard(max_accel=float(args[k + 1]))
        except (IndexError, ValueError):
            sys.exit(__doc__)
        del args[k:k + 2]
    if len(args) != 2 or any(a.startswith("--") for a in args) or guard.max_accel < 0:
        sys.exit(__doc__)
    try:
        if Path(args[1]).is_dir():
            raise D3LVOInputError(Path(args[1]), "is a folder; OUT.txt names the trajectory file to write")
        KittiSequence.open(args[0])  # the drive, then where its poses go, before it is tracked
        make_output_folder(Path(args[1]).parent, "OUT.txt's folder", "the trajectory")
        main(Path(args[0]), Path(args[1]), "--shadows" in sys.argv, guard)
    except D3LVOInputError as e:
        sys.exit(f"error: {e}")
