"""Where the first pair of a run starts: several guesses, the one whose solve explains frame t best.

Every later pair starts from the previous pair's motion (constant velocity), but the first has no
previous motion. From rest (the identity) a direct solve converges only within a basin of about a
metre and two degrees: a run that begins on a highway at 2.7 m per frame, or in the middle of a
turn at 3.5 deg per frame, locks onto a wrong pose, and its first rotation error bends the whole
trajectory. So the first pair is solved from a small grid of forward speeds and yaw rates, and
the solve kept is the one with the lowest median photometric residual of frame t-1's points in
frame t at full resolution, after the exposure change between the frames: a cost that needs no
learning, and one that no wrong basin scored lower on the drives measured (docs/evaluation.md).
`--method direct` keeps that solve; the network, in the runtime and in torch, starts its first
pair from it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .geometry import axis_angle_to_rot, se3_inv
from .points import bilinear, project


@dataclass(frozen=True)
class ColdStartConfig:
    # forward motion of the camera between two frames, m (KITTI at 10 Hz: up to ~2.8 m)
    forward_m: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0)
    # yaw per frame, degrees (KITTI's sharpest turns: ~4 deg per frame); 0 first: a tie keeps rest
    yaw_deg: tuple[float, ...] = (0.0, -3.0, 3.0)
    enabled: bool = True


def candidate_starts(cfg: ColdStartConfig) -> list[np.ndarray]:
    """Image_2 motions (frame t in frame t-1; z forward, yaw about the camera's y axis); the
    identity first."""
    if not cfg.enabled:
        return [np.eye(4)]
    starts = []
    for z in cfg.forward_m:
        for yaw in cfg.yaw_deg:
            A = np.eye(4)
            A[:3, :3] = axis_angle_to_rot(np.array([0.0, np.radians(yaw), 0.0]))
            A[2, 3] = z
            starts.append(A)
    return starts


def motion_samples(grey1: np.ndarray, points1: np.ndarray, grey2: np.ndarray, K: np.ndarray,
                   A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) float32 grey1 at frame t-1's points X, (N,) grey2 at pi(M X) (0 where outside), and (N,)
    whether M X lands in front of frame t's camera and inside its image; M = A^-1 (A: frame t in
    frame t-1, image_2). What a cost of the motion A compares."""
    M = se3_inv(A)
    X2 = points1 @ M[:3, :3].T + M[:3, 3]
    front = X2[:, 2] > 0.1
    uv2, _ = project(np.where(front[:, None], X2, 1.0), K)
    h, w = grey2.shape
    inside = front & (uv2[:, 0] >= 0) & (uv2[:, 0] <= w - 1) & (uv2[:, 1] >= 0) & (uv2[:, 1] <= h - 1)
    ref = bilinear(np.ascontiguousarray(grey1, np.float32), project(points1, K)[0])
    seen = bilinear(np.ascontiguousarray(grey2, np.float32), np.where(inside[:, None], uv2, 0.0))
    return ref, np.where(inside, seen, 0.0).astype(np.float32), inside


def photometric_cost(grey1: np.ndarray, points1: np.ndarray, grey2: np.ndarray, K: np.ndarray,
                     A: np.ndarray, min_points: int = 12) -> float:
    """Median |grey2(pi(M X)) - (a grey1(pi(X)) + b)| over frame t-1's points X that land in frame
    t, M = A^-1 (A: frame t in frame t-1, image_2), with gain a and offset b the least-squares fit
    of the one on the other. The fit: an exposure change shifts every residual alike, and without
    it the cost compares the exposure, not the poses (measured on a drive with sensor effects, a
    wrong basin then scored lower). The median, not the mean: what moves, up to half the points,
    does not decide it. inf where fewer than `min_points` land in view."""
    if len(points1) < min_points:
        return float("inf")
    ref, seen, inside = motion_samples(grey1, points1, grey2, K, A)
    if inside.sum() < min_points:
        return float("inf")
    ref, seen = ref[inside].astype(np.float64), seen[inside].astype(np.float64)
    dr = ref - ref.mean()
    gain = float(dr @ (seen - seen.mean()) / (dr @ dr)) if dr @ dr > 1e-12 else 0.0
    return float(np.median(np.abs(seen - seen.mean() - gain * dr)))


def best_start(starts: list[np.ndarray], solve: Callable[[np.ndarray], np.ndarray],
               cost: Callable[[np.ndarray], float]) -> np.ndarray:
    """The motion `solve` reaches from the start whose result costs least (the first on a tie).
    One start: its solve, uncosted."""
    solves = [solve(start) for start in starts]
    if len(solves) == 1:
        return solves[0]
    return solves[int(np.argmin([cost(A) for A in solves]))]
