"""A direct LiDAR-visual tracker with no learning: the reference the network must beat.

DVL-SLAM's tracking (Shin, Park, Kim 2018) in numpy: frame t-1's LiDAR returns are 3D points,
frame t's grey image is sampled where they project, and a Huber-weighted Gauss-Newton on SE(3)
minimises the photometric difference, coarse to fine over a smoothed image pyramid, starting
from the previous frame's motion (constant velocity). It sees the same network view (crop and
resize) as D3LVO, so the two are compared on equal pixels.

`DirectOdometry.register_frame(image, points)` reads as the algorithm; it has the streaming
interface of `Odometry` (`step`, `prime`, `reset`, `pose`), so `d3lvo run --method direct`
writes and scores its trajectory the same way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from .calib import Calib
from .frames import FramePreprocessor
from .geometry import axis_angle_to_rot, change_frame, relative, se3_inv, skew
from .odometry import FrameTiming, clean_scan


@dataclass
class DirectConfig:
    width: int = 608  # network view the tracker works on (the bundled model's input)
    height: int = 176
    strides: tuple[int, ...] = (8, 4, 2)  # pyramid, coarse to fine (pixels of the view per cell)
    iterations: int = 4  # Gauss-Newton iterations per level
    huber: float = 0.02  # on grey values in [0, 1]
    damping: float = 1e-3  # Levenberg-Marquardt lambda relative to diag(H)
    max_depth: float = 120.0


@dataclass
class Level:
    """One pyramid level of a frame: smoothed grey image sampled at cell centres, its gradients."""
    stride: int
    grey: np.ndarray
    gx: np.ndarray
    gy: np.ndarray


def pyramid(grey: np.ndarray, strides: tuple[int, ...]) -> list[Level]:
    """Box-smooth over stride+1 pixels and sample at multiples of the stride (cell i <-> pixel s*i)."""
    out = []
    for s in strides:
        g = cv2.blur(grey, (s + 1, s + 1), borderType=cv2.BORDER_REPLICATE)[::s, ::s] if s > 1 else grey
        g = np.ascontiguousarray(g, np.float32)
        gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=1, borderType=cv2.BORDER_REPLICATE) / 2.0
        gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=1, borderType=cv2.BORDER_REPLICATE) / 2.0
        out.append(Level(s, g, gx, gy))
    return out


def sample(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear sample at (u, v) in level pixels; 0 outside."""
    return cv2.remap(img, u.reshape(1, -1).astype(np.float32), v.reshape(1, -1).astype(np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)[0]


def level_points(depth: np.ndarray, K: np.ndarray, s: int) -> tuple[np.ndarray, np.ndarray]:
    """LiDAR pixels at the level's cell centres -> (N,3) points of that frame and their (N,2) cells."""
    d = depth[::s, ::s]
    i, j = np.nonzero(d > 0)
    z = d[i, j].astype(np.float64)
    u, v = j * s, i * s
    X = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
    return X, np.stack([j, i], 1)


def align_level(M: np.ndarray, X: np.ndarray, ref: np.ndarray, lvl: Level, K: np.ndarray, cfg: DirectConfig) -> np.ndarray:
    """Gauss-Newton on M (frame t-1 -> frame t points) for one level; left updates exp(xi) M."""
    fx, fy, cx, cy = K[0, 0] / lvl.stride, K[1, 1] / lvl.stride, K[0, 2] / lvl.stride, K[1, 2] / lvl.stride
    h, w = lvl.grey.shape
    for _ in range(cfg.iterations):
        Xt = X @ M[:3, :3].T + M[:3, 3]
        z = Xt[:, 2]
        ok = z > 0.1
        zi = np.where(ok, 1.0 / np.where(ok, z, 1.0), 0.0)
        u, v = fx * Xt[:, 0] * zi + cx, fy * Xt[:, 1] * zi + cy
        ok &= (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        if ok.sum() < 12:
            break
        r = sample(lvl.grey, u, v) - ref
        gu, gv = sample(lvl.gx, u, v), sample(lvl.gy, u, v)
        # d pixel / d point (2x3) times d point / d xi = [I | -[X']x]
        Jp = np.zeros((len(X), 2, 3))
        Jp[:, 0, 0], Jp[:, 0, 2] = fx * zi, -fx * Xt[:, 0] * zi * zi
        Jp[:, 1, 1], Jp[:, 1, 2] = fy * zi, -fy * Xt[:, 1] * zi * zi
        Jx = np.concatenate([np.broadcast_to(np.eye(3), (len(X), 3, 3)), -skew(Xt)], 2)
        J = np.einsum("ni,nij,njk->nk", np.stack([gu, gv], 1), Jp, Jx)
        a = np.abs(r)
        wgt = np.where(a <= cfg.huber, 1.0, cfg.huber / np.maximum(a, 1e-12)) * ok
        H = (J * wgt[:, None]).T @ J
        g = (J * wgt[:, None]).T @ r
        H[np.diag_indices(6)] += cfg.damping * np.diag(H) + 1e-9
        xi = -np.linalg.solve(H, g)
        dT = np.eye(4)
        dT[:3, :3] = axis_angle_to_rot(xi[3:])
        M = dT @ M
        M[:3, 3] += xi[:3]
    return M


@dataclass
class _Frame:
    levels: list[Level]
    depth: np.ndarray


@dataclass
class DirectOdometry:
    calib: Calib
    cfg: DirectConfig = field(default_factory=DirectConfig)

    def __post_init__(self) -> None:
        self.pre: FramePreprocessor | None = None
        self.last_timing = FrameTiming()
        self.reset()

    needs_scan = True

    def reset(self, start_pose: np.ndarray | None = None) -> None:
        self._prev: _Frame | None = None
        self.pose = np.eye(4) if start_pose is None else np.array(start_pose, dtype=np.float64)
        self.motion2 = np.eye(4)  # last image_2 motion: the constant-velocity start
        self.frames = 0

    def _frame(self, image: np.ndarray, points: np.ndarray | None) -> _Frame:
        t0 = time.perf_counter()
        if self.pre is None:
            h, w = image.shape[:2]
            self.pre = FramePreprocessor.create(self.calib, w, h, self.cfg.width, self.cfg.height, "sparse",
                                                self.cfg.max_depth)
        grey = self.pre.rgb(image).mean(2)
        depth = self.pre.depth(clean_scan(points))
        f = _Frame(pyramid(grey, self.cfg.strides), depth)
        self.last_timing = FrameTiming({"project": (time.perf_counter() - t0) * 1000})
        return f

    def register_frame(self, image: np.ndarray, points: np.ndarray | None) -> np.ndarray:
        """Track frame t against frame t-1's LiDAR points; returns the image_2 motion A (t in t-1)."""
        cur = self._frame(image, points)
        t0 = time.perf_counter()
        A = np.eye(4)
        if self._prev is not None:
            M = se3_inv(self.motion2)  # constant velocity
            for prev_lvl, lvl in zip(self._prev.levels, cur.levels):
                X, cells = level_points(self._prev.depth, self.pre.K, lvl.stride)
                ref = prev_lvl.grey[cells[:, 1], cells[:, 0]]
                M = align_level(M, X, ref, lvl, self.pre.K, self.cfg)
            A = se3_inv(M)
            self.motion2 = A
        self.last_timing.ms["flowpose"] = (time.perf_counter() - t0) * 1000
        self._prev = cur
        return A

    def step(self, image: np.ndarray, points: np.ndarray | None) -> np.ndarray:
        """Add a frame; returns its 4x4 cam0 pose in the first frame's coordinates."""
        first = self._prev is None
        A = self.register_frame(image, points)
        if not first:
            self.pose = self.pose @ change_frame(A, self.calib.T_cam0_cam2)
        self.frames += 1
        return self.pose.copy()

    def prime(self, image: np.ndarray, points: np.ndarray | None, pose: np.ndarray,
              previous_pose: np.ndarray | None = None) -> None:
        self._prev = self._frame(image, points)
        self.pose = np.array(pose, dtype=np.float64)
        if previous_pose is not None:
            self.motion2 = change_frame(relative(previous_pose, self.pose), self.calib.T_cam2_cam0)
        self.frames += 1
