"""Where the first pair of a run starts: several guesses, the one whose solve explains frame t best.

Every later pair starts from the previous pair's motion (constant velocity), but the first has no
previous motion. From rest (the identity) a direct solve converges only within a basin of about a
metre and two degrees: a run that begins on a highway at 2.7 m per frame, or in the middle of a
turn at 3.5 deg per frame, locks onto a wrong pose, and its first rotation error bends the whole
trajectory. So the first pair is solved from a small grid of forward speeds and yaw rates, and
the solve kept is the one with the lowest median photometric residual of frame t-1's points in
frame t at full resolution, after the exposure change between the frames: a cost that needs no
learning, and one that no wrong basin scored lower on the drives measured (docs/evaluation.md). Shared by `--method direct`, the runtime and the torch model, so
that the network and its classical reference start alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, TypeVar

import numpy as np

from .geometry import axis_angle_to_rot, se3_inv
from .points import bilinear, project

Solve = TypeVar("Solve")


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
    M = se3_inv(A)
    X2 = points1 @ M[:3, :3].T + M[:3, 3]
    front = X2[:, 2] > 0.1
    uv2, _ = project(np.where(front[:, None], X2, 1.0), K)
    h, w = grey2.shape
    inside = front & (uv2[:, 0] >= 0) & (uv2[:, 0] <= w - 1) & (uv2[:, 1] >= 0) & (uv2[:, 1] <= h - 1)
    if inside.sum() < min_points:
        return float("inf")
    ref = bilinear(np.ascontiguousarray(grey1, np.float32), project(points1[inside], K)[0]).astype(np.float64)
    seen = bilinear(np.ascontiguousarray(grey2, np.float32), uv2[inside]).astype(np.float64)
    dr = ref - ref.mean()
    gain = float(dr @ (seen - seen.mean()) / (dr @ dr)) if dr @ dr > 1e-12 else 0.0
    return float(np.median(np.abs(seen - seen.mean() - gain * dr)))


def best_start(starts: list[np.ndarray], solve: Callable[[np.ndarray], Solve],
               motion: Callable[[Solve], np.ndarray], cost: Callable[[np.ndarray], float]) -> tuple[Solve, int]:
    """Solve from each start and keep the solve whose motion costs least (the first on a tie);
    returns it and its start's index. One start: that solve, uncosted."""
    best, best_cost, best_i = None, float("inf"), 0
    for i, start in enumerate(starts):
        out = solve(start)
        if len(starts) == 1:
            return out, 0
        c = cost(motion(out))
        if best is None or c < best_cost:
            best, best_cost, best_i = out, c, i
    return best, best_i
