"""The first pair of each drive, from rest and from the cold start's guesses (`d3lvo_deploy.cold_start`).

    python scripts/first_pairs.py DRIVE...

Runs the classical tracker (`--method direct`) on frames 0-1 of each drive twice, started from
rest and from the guesses, and prints each start's translation and rotation error against the
drive's poses.txt, and the margin of the cost that picks the guess: the lowest cost of a guess
whose solve ends over 0.2 m off over the lowest of one within 5 cm (above 1: the right one wins;
blank where all or none converge). How the guesses were checked (docs/evaluation.md).
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

from d3lvo_deploy.cold_start import ColdStartConfig, candidate_starts
from d3lvo_deploy.direct import DirectConfig, DirectOdometry, motion_cost, track
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.geometry import change_frame, relative, rotation_angle_precise as rotation_angle
from d3lvo_deploy.sequence import KittiSequence


def first_pair(seq: KittiSequence, cfg: ColdStartConfig) -> tuple[np.ndarray, float]:
    """The cam0 motion of frame 1 in frame 0, and the solve's time (ms)."""
    odo = DirectOdometry(seq.calib, DirectConfig(cold_start=cfg))
    poses = [odo.step(seq.image(i), seq.scan(i)) for i in range(2)]
    return relative(poses[0], poses[1]), odo.last_timing.ms["flowpose"]


def margin(seq: KittiSequence, G: np.ndarray) -> str:
    """The lowest cost among guesses solved over 0.2 m off G over the lowest within 5 cm."""
    odo = DirectOdometry(seq.calib)
    prev = odo._frame(seq.image(0), seq.scan(0))
    cur = odo._frame(seq.image(1), seq.scan(1))
    right, wrong = [], []
    for start in candidate_starts(ColdStartConfig()):
        A = track(prev, cur, start, odo.cfg)
        cost = motion_cost(prev, cur, A)
        off = np.linalg.norm((np.linalg.inv(G) @ change_frame(A, seq.calib.T_cam0_cam2))[:3, 3])
        (right if off < 0.05 else wrong if off > 0.2 else []).append(cost)
    return f"{min(wrong) / min(right):.2f}" if right and wrong else ""


def main(drives: list[str]) -> None:
    warnings.simplefilter("ignore")
    print(f"{'drive':18s} {'step m':>7s} {'yaw deg':>8s} | from rest: m, deg, ms | from the guesses: m, deg, ms | margin")
    for drive in drives:
        try:
            seq = KittiSequence.open(drive)
        except D3LVOInputError as e:
            sys.exit(str(e))
        gt = seq.ground_truth
        if gt is None:
            sys.exit(f"{drive}: no poses.txt, the ground truth this script scores against")
        G = relative(gt.poses[0], gt.poses[1])
        row = f"{Path(drive).name:18s} {np.linalg.norm(G[:3, 3]):7.2f} {np.degrees(rotation_angle(G[:3, :3])):8.2f} |"
        for cfg in (ColdStartConfig(enabled=False), ColdStartConfig()):
            A, ms = first_pair(seq, cfg)
            E = np.linalg.inv(G) @ A
            row += f" {np.linalg.norm(E[:3, 3]):.3f} {np.degrees(rotation_angle(E[:3, :3])):.3f} {ms:.0f} |"
        print(row + " " + margin(seq, G), flush=True)
    print(f"guesses: {len(candidate_starts(ColdStartConfig()))} ({ColdStartConfig()})")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
