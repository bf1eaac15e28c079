"""Other ways of guarding the classical tracker's motion, beside the shipped motion guard.

    .venv/bin/python scripts/guard_variants.py VARIANT A DRIVE...
    .venv/bin/python scripts/guard_variants.py truth DRIVE...

Runs `d3lvo run DRIVE --method direct --max-accel A` (the bundled model's classical mode) with the
guard's decision changed, and prints each drive's t_rel (ATE where it has none) and the pairs
guarded. VARIANT: `hold` (the guard as it ships: the previous motion kept), `clamp` (the solved step
scaled to the nearest speed within the limit instead), `release:K` (the solve taken as it is after K
guarded pairs in a row), `scan` (the previous motion kept only where it fits frame t's own LiDAR
scan better than the solve, `direct.lidar_depth_error` over every point). `truth` prints the
largest change of step length between two pairs of each drive's ground truth, and its
acceleration at the drive's frame rate. docs/evaluation.md ("The motion guard") quotes both.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from d3lvo_deploy import direct
from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.direct import DirectConfig, DirectOdometry, lidar_depth_error
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.evaluation import evaluate
from d3lvo_deploy.geometry import relatives
from d3lvo_deploy.manifest import load_manifest
from d3lvo_deploy.motion_guard import MotionGuard, guard_motion
from d3lvo_deploy.sequence import KittiSequence


def truth(drive: Path) -> None:
    seq = KittiSequence.open(drive)
    if seq.ground_truth is None or len(seq) < 3:
        raise D3LVOInputError(drive, "has no poses.txt, or fewer than 3 frames")
    steps = np.linalg.norm(relatives(seq.ground_truth.poses)[:, :3, 3], axis=1)
    k = int(np.argmax(np.abs(np.diff(steps))))
    dt = float(np.median(np.diff(seq.times)))
    change = abs(steps[k + 1] - steps[k])
    print(f"{drive.name}: largest change of step {change:.3f} m (pairs {k + 1}, {k + 2}), {change / dt ** 2:.1f} m/s^2")


def run(variant: str, a: float, drive: Path) -> None:
    seq = KittiSequence.open(drive)
    if seq.ground_truth is None:
        raise D3LVOInputError(drive, "has no poses.txt")
    odo = DirectOdometry(seq.calib, DirectConfig.of_model(load_manifest(bundled_model_dir())["model_config"]),
                         MotionGuard(max_accel=a))
    state = {"row": 0, "judge": None}
    frame = odo._frame

    def framed(image, points):  # frame t, with frame t-1 still `odo._prev`: the scan's judgement
        cur, prev = frame(image, points), odo._prev
        state["judge"] = (None if prev is None or cur.depth is None else
                          lambda A: lidar_depth_error(prev.points, A, cur.depth, prev.levels[0].K))
        return cur

    def decided(A, dt, previous, previous_dt, guard):
        kept, held = guard_motion(A, dt, previous, previous_dt, guard)
        state["row"] = state["row"] + 1 if held else 0
        if not held or variant == "hold":
            return kept, held
        if variant == "clamp":
            v0 = np.linalg.norm(previous[:3, 3]) / previous_dt
            v = np.clip(np.linalg.norm(A[:3, 3]) / dt, v0 - guard.max_accel * dt, v0 + guard.max_accel * dt)
            clamped = A.copy()
            clamped[:3, 3] *= v * dt / max(float(np.linalg.norm(A[:3, 3])), 1e-12)
            return clamped, True
        if variant.startswith("release:") and state["row"] > int(variant.split(":")[1]):
            state["row"] = 0
            return A, False
        if variant == "scan" and state["judge"] is not None and not state["judge"](kept) < state["judge"](A):
            return A, False
        return kept, held

    odo._frame = framed
    direct.guard_motion = decided
    try:
        poses = np.stack([odo.step(seq.image(i), seq.scan(i), float(seq.times[i])) for i in range(len(seq))])
    finally:
        direct.guard_motion = guard_motion
    e = evaluate(seq.ground_truth.poses, poses)
    score = f"t_rel {e.t_rel:.2f} %" if e.t_rel is not None else f"ATE {e.ate:.3f} m"
    print(f"{drive.name}: {variant} at {a:g} m/s^2: {score}, {odo.guarded} pairs guarded")


if __name__ == "__main__":
    args = sys.argv[1:]
    variant = args[0] if args else ""
    try:
        limit = float(args[1]) if len(args) >= 3 else -1.0
        int(variant.split(":")[1]) if variant.startswith("release:") else 0
    except ValueError:
        sys.exit(__doc__)
    try:
        if variant == "truth" and len(args) > 1:
            for d in args[1:]:
                truth(Path(d))
        elif limit >= 0 and (variant in ("hold", "clamp", "scan") or variant.startswith("release:")):
            for d in args[2:]:
                run(variant, limit, Path(d))
        else:
            sys.exit(__doc__)
    except D3LVOInputError as e:
        sys.exit(f"error: {e}")
