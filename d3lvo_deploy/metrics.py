"""Odometry metrics as pure functions.

`segment_errors` follows the KITTI odometry devkit (evaluate_odometry.cpp) step by step, including
its single-precision path lengths, so t_rel / r_rel match the official numbers. ATE and RPE follow
kitti-odom-eval (ATE: RMSE of positions; RPE: mean frame-to-frame error).
"""

from __future__ import annotations

import numpy as np

from .geometry import relative, rotation_angle_precise, se3_inv

SEGMENT_LENGTHS = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
STEP_SIZE = 10  # a new segment starts every 10 frames (one second at 10 Hz)


def trajectory_distances(poses: np.ndarray) -> np.ndarray:
    """Cumulative path length, accumulated in float32 exactly as the devkit's vector<float> does."""
    p = np.asarray(poses, dtype=np.float64)[:, :3, 3]
    steps = np.sqrt(((p[1:] - p[:-1]) ** 2).sum(1))
    dist = np.zeros(len(p), dtype=np.float32)
    acc = np.float32(0.0)
    for i, s in enumerate(steps, 1):
        acc = np.float32(np.float64(acc) + s)
        dist[i] = acc
    return dist


def last_frame_from_segment_length(dist: np.ndarray, first: int, length: float) -> int:
    """First frame whose path length exceeds dist[first] + length, or -1."""
    target = np.float32(dist[first]) + np.float32(length)
    idx = np.nonzero(dist[first:] > target)[0]
    return int(first + idx[0]) if len(idx) else -1


def segment_errors(gt: np.ndarray, est: np.ndarray, valid: np.ndarray | None = None,
                   lengths: tuple[float, ...] = SEGMENT_LENGTHS, step: int = STEP_SIZE) -> np.ndarray:
    """Devkit segment errors; rows (first_frame, r_err rad/m, t_err m/m, length m, speed m/s).

    `valid[i]` False marks frames without an estimate (kitti-odom-eval's skipped frames): segments
    starting or ending there are left out.
    """
    gt = np.asarray(gt, dtype=np.float64)
    est = np.asarray(est, dtype=np.float64)
    dist = trajectory_distances(gt)
    rows = []
    for first in range(0, len(gt), step):
        for length in lengths:
            last = last_frame_from_segment_length(dist, first, length)
            if last == -1 or (valid is not None and not (valid[first] and valid[last])):
                continue
            # general inverses, as the devkit's Matrix::inv: GT rotations are not exactly orthonormal
            delta_gt = np.linalg.inv(gt[first]) @ gt[last]
            delta_est = np.linalg.inv(est[first]) @ est[last]
            err = np.linalg.inv(delta_est) @ delta_gt
            length32 = np.float32(length)
            rows.append((first, _devkit_rotation_error(err) / length32, _devkit_translation_error(err) / length32,
                         length, length / (0.1 * (last - first + 1))))
    return np.asarray(rows, dtype=np.float64).reshape(-1, 5)


def _devkit_rotation_error(err: np.ndarray) -> np.float32:
    """acos of a float32 trace term: the devkit's quantisation of small angles is kept on purpose."""
    a, b, c = (np.float32(err[i, i]) for i in range(3))
    d = np.float32(0.5 * (np.float64(a) + np.float64(b) + np.float64(c) - 1.0))
    return np.float32(np.arccos(np.float64(min(max(d, np.float32(-1.0)), np.float32(1.0)))))


def _devkit_translation_error(err: np.ndarray) -> np.float32:
    dx, dy, dz = (np.float32(err[i, 3]) for i in range(3))
    return np.float32(np.sqrt(dx * dx + dy * dy + dz * dz))


def rel_errors(segments: np.ndarray) -> tuple[float, float]:
    """(t_rel %, r_rel deg/100 m) as the devkit reports them: float32 running means over segments."""
    if len(segments) == 0:
        return float("nan"), float("nan")
    n = np.float32(len(segments))
    t = np.cumsum(segments[:, 2].astype(np.float32), dtype=np.float32)[-1] / n
    r = np.cumsum(segments[:, 1].astype(np.float32), dtype=np.float32)[-1] / n
    return float(t) * 100.0, float(np.degrees(np.float64(r))) * 100.0


def ate_rmse(gt: np.ndarray, est: np.ndarray) -> float:
    """RMSE of position differences (metres); align the estimate first if wanted."""
    d = np.asarray(gt)[:, :3, 3] - np.asarray(est)[:, :3, 3]
    return float(np.sqrt((d**2).sum(1).mean()))


def rpe_from_motions(gt_rel: np.ndarray, est_rel: np.ndarray) -> tuple[float, float]:
    """Mean error between paired relative motions: (translation m, rotation deg)."""
    if len(gt_rel) == 0:
        return float("nan"), float("nan")
    e = se3_inv(np.asarray(gt_rel, dtype=np.float64)) @ np.asarray(est_rel, dtype=np.float64)
    return float(np.linalg.norm(e[:, :3, 3], axis=1).mean()), float(np.degrees(rotation_angle_precise(e[:, :3, :3])).mean())


def rpe(gt: np.ndarray, est: np.ndarray, delta: int = 1) -> tuple[float, float]:
    """Mean relative pose error over `delta` frames: (translation m, rotation deg)."""
    gt = np.asarray(gt, dtype=np.float64)
    est = np.asarray(est, dtype=np.float64)
    return rpe_from_motions(relative(gt[:-delta], gt[delta:]), relative(est[:-delta], est[delta:]))


def auroc(scores: np.ndarray, labels: np.ndarray) -> float | None:
    """Area under the ROC curve of `scores` ranking the positives (labels True) first: the
    Mann-Whitney U statistic over average ranks, so ties count one half. None without both classes."""
    s = np.asarray(scores, dtype=np.float64).ravel()
    y = np.asarray(labels, dtype=bool).ravel()
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return None
    order = np.argsort(s, kind="mergesort")
    ranks = np.empty(len(s))
    sorted_s = s[order]
    # average rank of each run of equal scores
    edges = np.flatnonzero(np.diff(sorted_s)) + 1
    starts, ends = np.concatenate([[0], edges]), np.concatenate([edges, [len(s)]])
    for a, b in zip(starts, ends):
        ranks[order[a:b]] = (a + b + 1) / 2.0
    return float((ranks[y].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))
