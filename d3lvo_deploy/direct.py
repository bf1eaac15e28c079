"""A direct LiDAR-visual tracker with no learning: the reference the network must beat.

DVL-SLAM's tracking (Shin, Park, Kim 2018) in numpy, as strong as we can make it without
learning: the LiDAR returns of frame t-1 that land on image texture (an evenly spaced 2,048 at
most, `points.py`) are 3D points (no pooling to cells, no resizing of the image); frame t's grey image, at its full resolution and two
pyrDown levels, is sampled where the points project, and Gauss-Newton on SE(3) minimises the
photometric difference, coarse to fine, up to `iterations` steps per level with an early stop,
from a constant-velocity start (the first pair from several, `cold_start`). The robust weight is Huber's with its threshold re-estimated
from the residuals every third step (1.345 x the MAD scale), so it follows the scene instead of a
fixed threshold that suits one exposure and one amount of noise. With `fine_restart` the finest
level is also solved alone from the start, and that motion is kept where it explains the points
better (`consensus_gain`), or with `restart_depth` where it fits frame t's own LiDAR scan better
(`lidar_depth_error`): a quarter-size level can hold a wrong minimum the finest cannot leave.
With `scan_gate`, frame t's scan first drops the points of frame t-1 that are no longer where the
starting motion puts them: what moves, before the solve can follow it.
With a `motion_guard` (off by default), a step whose speed no car reaches from the last one's is
replaced by the last.

`DirectOdometry.register_frame(image, points)` reads as the algorithm; it has the streaming
interface of `Odometry` (`step`, `prime`, `reset`, `pose`), so `d3lvo run --method direct`
writes and scores its trajectory the same way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from .blas import one_blas_thread
from .calib import Calib
from .cold_start import ColdStartConfig, best_start, candidate_starts, motion_samples, photometric_cost
from .geometry import axis_angle_to_rot, change_frame, relative, se3_inv
from .motion_guard import MotionGuard, guard_motion, scaled_motion
from .odometry import (FrameTiming, as_calib, as_stamp, calib_source, check_first_frame, check_frame_size,
                       check_image, check_texture, clean_scan, rigid_pose)
from .points import PointConfig, bilinear as sample, grey_image, gradients, point_config, project, textured_points
from .projection import PROJECTION_MIN_DEPTH, rows_in_view, sparse_depth

MAD_TO_SIGMA = 1.4826  # MAD of a normal distribution times this is its standard deviation
HUBER_K = 1.345  # Huber's threshold in sigmas: 95 % efficiency on Gaussian residuals


@dataclass
class DirectConfig:
    levels: int = 3  # pyramid levels: the full image and (levels - 1) pyrDown halvings
    # most Gauss-Newton steps per level, coarse to fine (measured in docs/evaluation.md: fewer
    # cost accuracy on drives with traffic, and 10 do not converge from a cold start of 0.9 m)
    iterations: tuple[int, ...] = (15, 15, 15)
    stop_step: float = 1e-6  # stop a level when the step moves no point by more than ~this (m, rad)
    damping: float = 1e-4  # Levenberg-Marquardt lambda relative to diag(H)
    # the Huber threshold from the residuals' median at every this-th step of a level, kept in
    # between: the median is a partial sort in the network's graph, its dearest node on OpenVINO
    scale_every: int = 3
    # that median over the points in view whose place in the point list is a multiple of this
    # (the network's `pt_median_stride`: its partial sort's time grows with the list)
    median_stride: int = 1
    # after the finest level, up to this many more steps there (the network's `pt_refine`, whose
    # restored weights are all 1 here, so that its classical mode stays this tracker)
    refine: int = 0
    points: PointConfig = field(default_factory=PointConfig)  # which LiDAR returns are tracked
    # match frame t's grey to frame t-1's mean and spread at every step (exposure changes; the
    # network's `pt_affine`, docs/evaluation.md)
    affine_brightness: bool = False
    # above 0: also solve the finest level alone from the start, and keep that motion where it
    # explains frame t-1's points better than coarse to fine's by more than this
    # (`consensus_gain`): a coarse level (a quarter of the image's width) can hold a wrong minimum,
    # and a constant-velocity start is near the truth at 10 Hz (the network's `pt_fine_restart`,
    # docs/evaluation.md)
    fine_restart: float = 0.0
    # above 0 (with `fine_restart`): also keep the restart where its `lidar_depth_error` against
    # frame t's own scan is below this times coarse to fine's: where few points constrain the
    # forward step, the photometric costs can prefer a motion half a metre short, and the scan
    # sees the step (the network's `pt_restart_depth`, docs/evaluation.md)
    restart_depth: float = 0.0
    # above 0: before a pair is solved, frame t-1's points that frame t's own LiDAR scan puts more
    # than this (relative depth) away from where the starting motion moves them are dropped
    # (`scan_gated`): at 10 Hz the start is near the truth for what stands still, and what moves
    # has left its place; it reads no image, so a vehicle the solve would follow is already gone
    # (the network's `pt_scan_gate`, docs/evaluation.md)
    scan_gate: float = 0.0
    # the first pair, which has no previous motion, from several guesses (`cold_start`)
    cold_start: ColdStartConfig = field(default_factory=ColdStartConfig)

    @property
    def restarts(self) -> bool:
        """The finest level is also solved alone from the start."""
        return self.fine_restart > 0 and self.levels > 1

    @property
    def checks_restart_on_scan(self) -> bool:
        """The restart is also judged by frame t's LiDAR depth, which each frame then keeps."""
        return self.restarts and self.restart_depth > 0

    @property
    def reads_scan(self) -> bool:
        """Each frame keeps its own LiDAR depth: for the restart's check or the scan gate."""
        return self.checks_restart_on_scan or self.scan_gate > 0

    @classmethod
    def of_model(cls, model_config: dict) -> "DirectConfig":
        """The classical mode of a point-solver model (its manifest's `model_config`): the same
        points, pyramid, iteration counts, stop and damping, with every confidence 1."""
        if model_config.get("pose_head") != "points":
            return cls()
        iters = tuple(model_config["pt_iters"])
        return cls(levels=len(iters), iterations=iters, stop_step=model_config["pt_stop"],
                   damping=model_config["pt_damping"], scale_every=model_config.get("pt_scale_every", 1),
                   median_stride=model_config.get("pt_median_stride", 1),
                   refine=model_config.get("pt_refine", 0), points=point_config(model_config),
                   affine_brightness=bool(model_config.get("pt_affine", False)),
                   fine_restart=float(model_config.get("pt_fine_restart", 0.0)),
                   restart_depth=float(model_config.get("pt_restart_depth", 0.0)),
                   scan_gate=float(model_config.get("pt_scan_gate", 0.0)))


@dataclass
class Level:
    """One pyramid level: grey image and its gradients stacked as 3 channels, and the intrinsics."""
    stack: np.ndarray  # (h, w, 3) float32: grey, d/du, d/dv
    K: np.ndarray  # (3, 3)

    @property
    def shape(self) -> tuple[int, int]:
        return self.stack.shape[:2]


def level_intrinsics(K: np.ndarray, level: int) -> np.ndarray:
    """Intrinsics after `level` pyrDown halvings: pyrDown centres its 5-tap kernel on source pixel
    2 x, so level pixel x sits at source pixel 2 x (not at 2 x + 0.5 as for an area resize)."""
    Kl = np.array(K, dtype=np.float64)
    Kl[:2] *= 0.5 ** level
    return Kl


def pyramid(grey: np.ndarray, K: np.ndarray, levels: int) -> list[Level]:
    """Finest first: level 0 is the image itself."""
    out, g = [], np.ascontiguousarray(grey, np.float32)
    for lvl in range(levels):
        if lvl:
            g = cv2.pyrDown(g)
        gx, gy = gradients(g)
        out.append(Level(np.dstack([g, gx, gy]), level_intrinsics(K, lvl)))
    return out


def huber_threshold(r: np.ndarray) -> float:
    """HUBER_K robust sigmas (1.4826 x the median |r|) of these residuals."""
    return max(HUBER_K * MAD_TO_SIGMA * float(np.median(np.abs(r))), 1e-6)


def stride_threshold(r: np.ndarray, index: np.ndarray, stride: int) -> float:
    """`huber_threshold` of the residuals r of the points at `index` in the point list, over those
    whose index is a multiple of `stride`; with none of them, no threshold (every weight 1), as
    the network's masked median of nothing."""
    sample = r[index % stride == 0] if stride > 1 else r
    return huber_threshold(sample) if len(sample) else np.inf


def huber_weights(r: np.ndarray, k: float | None = None) -> np.ndarray:
    """Huber weights at threshold k, by default `huber_threshold(r)`."""
    a = np.abs(r)
    k = huber_threshold(r) if k is None else k
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def affine_fit(ref: np.ndarray, cur: np.ndarray, w: np.ndarray) -> np.ndarray:
    """a ref + b with the w-weighted mean and spread of cur: the exposure and gain change between
    the frames. Matched moments rather than a least-squares fit of cur on ref: far from the
    solution the two do not correlate, a least-squares gain goes to 0 and the residual no longer
    depends on the pose."""
    sw = max(float(w.sum()), 1e-30)
    mr, mc = (w * ref).sum() / sw, (w * cur).sum() / sw
    vr, vc = (w * (ref - mr) ** 2).sum() / sw, (w * (cur - mc) ** 2).sum() / sw
    return np.sqrt(max(vc, 1e-30) / max(vr, 1e-30)) * (ref - mr) + mc


def align_level(M: np.ndarray, X: np.ndarray, ref: np.ndarray, lvl: Level, iterations: int,
                cfg: DirectConfig, index: np.ndarray | None = None) -> np.ndarray:
    """Gauss-Newton on M (frame t-1 points -> frame t) at one level; left updates exp(xi) M.
    index: each point's place in the point list (`TrackedFrame.index`), for the median's stride."""
    h, w = lvl.shape
    fx, fy = lvl.K[0, 0], lvl.K[1, 1]
    for i in range(iterations):
        Xt = X @ M[:3, :3].T + M[:3, 3]
        front = Xt[:, 2] > 0.1
        uv, zi = project(np.where(front[:, None], Xt, 1.0), lvl.K)
        ok = front & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        if ok.sum() < 12:
            break
        Xt, uv, zi = Xt[ok], uv[ok], zi[ok]
        s = sample(lvl.stack, uv)
        # with affine_brightness, frame t's grey against frame t-1's matched on every point in
        # view, the Huber threshold from that, then matched again with the Huber weights, as the
        # network's solver does
        cur = s[:, 0]
        r = cur - (affine_fit(ref[ok], cur, np.ones_like(cur)) if cfg.affine_brightness else ref[ok])
        if i % cfg.scale_every == 0:
            k = stride_threshold(r, np.flatnonzero(ok) if index is None else index[ok], cfg.median_stride)
        if cfg.affine_brightness:
            r = cur - affine_fit(ref[ok], cur, huber_weights(r, k))
        # d residual / d point = grad . d pixel / d point; rotation part = X' x a (left perturbation)
        a = np.stack([s[:, 1] * fx * zi, s[:, 2] * fy * zi,
                      -(s[:, 1] * fx * Xt[:, 0] + s[:, 2] * fy * Xt[:, 1]) * zi * zi], 1)
        J = np.concatenate([a, np.cross(Xt, a)], 1)
        Jw = J * huber_weights(r, k)[:, None]
        H, g = Jw.T @ J, Jw.T @ r
        H[np.diag_indices(6)] *= 1.0 + cfg.damping
        xi = -np.linalg.solve(H + 1e-12 * np.eye(6), g)
        dT = np.eye(4)
        dT[:3, :3] = axis_angle_to_rot(xi[3:])
        dT[:3, 3] = xi[:3]
        M = dT @ M
        if np.abs(xi).max() < cfg.stop_step:
            break
    return M


@dataclass
class TrackedFrame:
    """What the tracker keeps of a frame: its image pyramid and its textured LiDAR returns."""
    levels: list[Level]
    points: np.ndarray  # (N, 3) textured LiDAR returns in image_2 camera coordinates
    # (H, W) metres of the frame's own LiDAR returns at the camera's resolution, 0 where none
    # (`DirectConfig.restart_depth`, `DirectConfig.scan_gate`); None where not needed
    depth: np.ndarray | None = None
    # each point's place in the frame's point list where `scan_gated` dropped some (the Huber
    # median's stride counts places in that list, as the network's graph does); None: 0 .. N-1
    index: np.ndarray | None = None

    @classmethod
    def of(cls, grey: np.ndarray, points: np.ndarray, K: np.ndarray, levels: int,
           depth: np.ndarray | None = None) -> "TrackedFrame":
        return cls(pyramid(grey, K, levels), points, depth)


def track(prev: TrackedFrame, cur: TrackedFrame, start: np.ndarray, cfg: DirectConfig) -> np.ndarray:
    """The image_2 motion A (frame t in t-1) that aligns frame t-1's points with frame t, coarse to
    fine from `start`."""
    if cfg.scan_gate > 0 and cur.depth is not None:
        prev = scan_gated(prev, cur.depth, start, cfg.scan_gate)
    M, X = se3_inv(start), prev.points
    for lvl in reversed(range(cfg.levels)):
        prev_lvl = prev.levels[lvl]
        ref = sample(prev_lvl.stack[..., :1], project(X, prev_lvl.K)[0])[:, 0]
        M = align_level(M, X, ref, cur.levels[lvl], cfg.iterations[cfg.levels - 1 - lvl], cfg, prev.index)

    def refined(M: np.ndarray) -> np.ndarray:
        return align_level(M, X, ref, cur.levels[0], cfg.refine, cfg, prev.index) if cfg.refine else M

    A = se3_inv(refined(M))
    if cfg.restarts:
        restart = se3_inv(refined(align_level(se3_inv(start), X, ref, cur.levels[0], cfg.iterations[-1], cfg,
                                              prev.index)))
        if keeps_restart(prev, cur, restart, A, cfg):
            A = restart
    return A


def keeps_restart(prev: TrackedFrame, cur: TrackedFrame, restart: np.ndarray, A: np.ndarray,
                  cfg: DirectConfig) -> bool:
    """The finest level's restart replaces the coarse-to-fine motion A where it explains frame t-1's
    points better by more than `fine_restart`, or (`restart_depth`) where it fits frame t's own
    LiDAR scan better by that ratio."""
    if consensus_gain(prev, cur, restart, A) > cfg.fine_restart:
        return True
    if not cfg.checks_restart_on_scan or cur.depth is None:
        return False
    K = prev.levels[0].K
    return (lidar_depth_error(prev.points, restart, cur.depth, K)
            < cfg.restart_depth * lidar_depth_error(prev.points, A, cur.depth, K))


def depth_errors(points: np.ndarray, A: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Per point of frame t-1 (N, 3) moved by the image_2 motion A (frame t in t-1), |d - z| / z
    against frame t's own LiDAR depth `depth` (H, W metres, 0 where none) at its nearest pixel;
    NaN where that pixel has no return, or z is 0.5 m or less (no evidence)."""
    M = se3_inv(A)
    X = points @ M[:3, :3].T + M[:3, 3]
    errors = np.full(len(points), np.nan)
    front = X[:, 2] > 0.5
    u, v = np.rint(project(np.where(front[:, None], X, 1.0), K)[0]).T
    at = np.flatnonzero(front & (u >= 0) & (u <= depth.shape[1] - 1) & (v >= 0) & (v <= depth.shape[0] - 1))
    d = depth[v[at].astype(int), u[at].astype(int)]
    seen = d > 0
    z = X[at[seen], 2]
    errors[at[seen]] = np.abs(d[seen] - z) / z
    return errors


def lidar_depth_error(points: np.ndarray, A: np.ndarray, depth: np.ndarray, K: np.ndarray) -> float:
    """The median `depth_errors` of frame t-1's points (N, 3) under the image_2 motion A; inf
    where none has evidence. A check of the motion that does not read the images and that sees
    the forward step (the network's `models.point_solver.lidar_depth_error` with every point
    trusted)."""
    errors = depth_errors(points, A, depth, K)
    seen = errors[~np.isnan(errors)]
    return float(np.median(seen)) if len(seen) else float("inf")


def scan_gated(prev: TrackedFrame, depth: np.ndarray, start: np.ndarray, limit: float) -> TrackedFrame:
    """Frame t-1 without the points whose `depth_errors` under the starting motion exceed `limit`:
    frame t's scan sees something else where they should be (they moved, or a mover now hides
    them). A point without evidence stays."""
    moved = np.nan_to_num(depth_errors(prev.points, start, depth, prev.levels[0].K), nan=0.0) > limit
    if not moved.any():
        return prev
    index = np.arange(len(prev.points)) if prev.index is None else prev.index
    return TrackedFrame(prev.levels, prev.points[~moved], prev.depth, index[~moved])


def consensus_gain(prev: TrackedFrame, cur: TrackedFrame, A: np.ndarray, B: np.ndarray, cap: float = 2.0) -> float:
    """How much better the image_2 motion A explains frame t-1's points than B: the mean over the
    points in view under both of min(r^2, c^2) under B minus the same under A, c = `cap` robust
    sigmas (1.4826 x the smaller median |r| of the two), in units of c^2 (RANSAC's MSAC cost; the
    network's `models.point_solver.consensus_gain` with every weight 1). A median alone scores a
    pose stuck near its start in rotation below the truth on some static pairs; the capped mean
    does not (docs/evaluation.md)."""
    finest, grey2 = prev.levels[0], cur.levels[0].stack[..., 0]
    ref, seen, ok = motion_samples(finest.stack[..., 0], prev.points, grey2, finest.K, A)
    _, seen_b, ok_b = motion_samples(finest.stack[..., 0], prev.points, grey2, finest.K, B)
    ok &= ok_b
    if not ok.any():
        return 0.0
    r, r_b = (seen - ref)[ok], (seen_b - ref)[ok]
    limit = max(cap * MAD_TO_SIGMA * min(np.median(np.abs(r)), np.median(np.abs(r_b))), 1e-6) ** 2
    return float(np.mean(np.minimum(r_b * r_b / limit, 1.0) - np.minimum(r * r / limit, 1.0)))


def first_motion(prev: TrackedFrame, cur: TrackedFrame, cfg: DirectConfig) -> np.ndarray:
    """`track` for a pair with no previous motion: from each of the cold start's guesses, keeping
    the motion with the lowest `photometric_cost`. The network's first pair starts from it too, so
    that its confidence reads the evidence against a motion near the truth, as on every other pair."""
    return best_start(candidate_starts(cfg.cold_start), lambda A0: track(prev, cur, A0, cfg),
                      lambda A: motion_cost(prev, cur, A))


def motion_cost(prev: TrackedFrame, cur: TrackedFrame, A: np.ndarray) -> float:
    """`photometric_cost` of the image_2 motion A on the pair's finest level."""
    finest = prev.levels[0]
    return photometric_cost(finest.stack[..., 0], prev.points, cur.levels[0].stack[..., 0], finest.K, A)


@dataclass
class DirectOdometry:
    """The classical tracker with `Odometry`'s streaming interface (`step`, `reset`, `relative`,
    `last_timing`) and its input checks. `calib`: a Calib or the path of a calibration file."""

    calib: Calib
    cfg: DirectConfig = field(default_factory=DirectConfig)
    guard: MotionGuard = field(default_factory=MotionGuard)  # `motion_guard`: off unless given

    def __post_init__(self) -> None:
        if len(self.cfg.iterations) != self.cfg.levels:
            raise ValueError(f"DirectConfig: {self.cfg.levels} levels but {len(self.cfg.iterations)} iteration counts")
        given, self.calib = self.calib, as_calib(self.calib)
        self.calib_source = calib_source(given)
        self.fit_checked = False  # `check_first_frame`
        self.last_timing = FrameTiming()
        self.reset()

    needs_scan = True
    scan_source = "scan"  # what a scan warning names (`d3lvo run` sets the frame)

    def reset(self, start_pose: np.ndarray | None = None) -> None:
        self._prev: TrackedFrame | None = None
        self.pose = np.eye(4) if start_pose is None else rigid_pose(start_pose, "reset's start_pose")
        self.relative = np.eye(4)  # the last frame-to-frame motion in cam0
        self.motion2 = np.eye(4)  # last image_2 motion: the constant-velocity start
        self.cold = True  # no previous motion yet: the first pair starts from `cold_start`'s guesses
        self.fit_checked = False  # a reset may start another recording: its first frame is checked again
        self.frames = 0
        self.motion_dt = self.guard.period  # the time of `motion2`
        self._prev_stamp: float | None = None
        self.guarded = 0  # pairs where the motion guard kept the previous motion

    def _frame(self, image: np.ndarray, points: np.ndarray | None) -> TrackedFrame:
        t0 = time.perf_counter()
        if not (isinstance(image, np.ndarray) and image.ndim == 2 and image.dtype == np.uint8):
            check_image(image)  # RGB, or the (H,W) grey the tracker reads anyway
        if self._prev is not None:
            check_frame_size(image, *self._prev.levels[0].shape[::-1])
        scan = clean_scan(points, self.scan_source)
        check_first_frame(self, image, scan)
        grey = grey_image(image)
        levels = pyramid(grey, self.calib.K2, self.cfg.levels)
        P, (h, w) = self.calib.P_velo_to_image2, grey.shape
        scan = rows_in_view(scan, P, w, h, min(PROJECTION_MIN_DEPTH, self.cfg.points.min_depth))
        X = textured_points(scan, self.calib.T_cam2_velo, self.calib.K2, grey, self.cfg.points,
                            grads=levels[0].stack[..., 1:])
        check_texture(X, scan, self.cfg.points, self.calib.T_cam2_velo, self.scan_source)
        depth = sparse_depth(scan, P, w, h) if self.cfg.reads_scan else None
        self.last_timing = FrameTiming({"project": (time.perf_counter() - t0) * 1000})
        return TrackedFrame(levels, X, depth)

    def register_frame(self, image: np.ndarray, points: np.ndarray | None, stamp: float | None = None) -> np.ndarray:
        """Track frame t against frame t-1's LiDAR points; returns the image_2 motion A (t in t-1).
        `stamp`: frame t's time in seconds, for the motion guard."""
        stamp = as_stamp(stamp)
        cur = self._frame(image, points)
        t0 = time.perf_counter()
        A = np.eye(4)
        dt = self.guard.interval(self._prev_stamp, stamp)
        if self._prev is not None and len(self._prev.points):
            if self.cold:
                A = first_motion(self._prev, cur, self.cfg)
            else:
                # constant velocity over this pair's time: a dropped frame's pair starts twice as far
                A = track(self._prev, cur, scaled_motion(self.motion2, dt / self.motion_dt), self.cfg)
                A, held = guard_motion(A, dt, self.motion2, self.motion_dt, self.guard)
                self.guarded += held
            self.motion2, self.motion_dt, self.cold = A, dt, False
        self.last_timing.ms["flowpose"] = (time.perf_counter() - t0) * 1000
        self._prev = cur
        self._prev_stamp = None if stamp is None else float(stamp)
        return A

    def step(self, image: np.ndarray, points: np.ndarray | None, stamp: float | None = None) -> np.ndarray:
        """Add a frame; returns its 4x4 cam0 pose in the first frame's coordinates. numpy's BLAS
        on one thread, as the network's frame work (`blas`): its products are small, and idle
        BLAS threads would spin on the other core. `stamp` as `Odometry.step`'s."""
        first = self._prev is None
        with one_blas_thread():
            A = self.register_frame(image, points, stamp)
        if not first:
            self.relative = change_frame(A, self.calib.T_cam0_cam2)
            self.pose = self.pose @ self.relative
        self.frames += 1
        return self.pose.copy()

    def prime(self, image: np.ndarray, points: np.ndarray | None, pose: np.ndarray,
              previous_pose: np.ndarray | None = None, stamp: float | None = None,
              previous_stamp: float | None = None) -> None:
        pose = rigid_pose(pose, "prime's pose")
        previous_pose = None if previous_pose is None else rigid_pose(previous_pose, "prime's previous_pose")
        stamp, previous_stamp = as_stamp(stamp, "prime's stamp"), as_stamp(previous_stamp, "prime's previous_stamp")
        self._prev = self._frame(image, points)
        self._prev_stamp = stamp
        self.pose = pose
        # without the pose before, no motion: the next pair starts from the cold start's guesses
        self.cold, self.motion2, self.relative = True, np.eye(4), np.eye(4)
        if previous_pose is not None:
            self.relative = relative(previous_pose, self.pose)
            self.motion2 = change_frame(self.relative, self.calib.T_cam2_cam0)
            self.motion_dt = self.guard.interval(previous_stamp, stamp)
            self.cold = False
        self.frames += 1
