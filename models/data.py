"""Training pairs from KITTI-format sequences (real KITTI or `d3lvo synth` output).

A sample is frames (t-1, t) at the network resolution: RGB in [0,1], the depth input the config
asks for (sparse LiDAR, IP-Basic dense, or nothing), a depth target, the GT relative pose of the
image_2 camera, the optical-flow target and, where the sequence has `motion_2/`, the mask of
pixels on moving vehicles. The flow target is the true flow where the sequence has `flow_2/`
(`d3lvo synth --traffic`: vehicles move on their own), else the rigid flow of the GT motion,
which is the true flow of a static world. The depth target is the renderer's z-buffer where the
sequence has `depth_2/`; else (real KITTI) a random fifth of the LiDAR returns, held out of the
depth input, so that completion is supervised where it has to guess rather than where it copies.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.geometry import change_frame, relative, rot_to_quat
from d3lvo_deploy.frames import FramePreprocessor
from d3lvo_deploy.odometry import clean_scan
from d3lvo_deploy.points import SolverFrame, point_config, solver_feeds
from d3lvo_deploy.projection import View, sparse_depth
from d3lvo_deploy.sequence import KittiSequence
from d3lvo_deploy.synth.generator import decode_kitti_flow, drive_traffic

from .augment import flip_images, flip_pose, roll_pose, rotate_images
from .config import D3LVOConfig


@dataclass
class AugmentConfig:
    flip: float = 0.5  # probability
    brightness: float = 0.2  # factor in [1 - b, 1 + b], shared by both frames
    rotation_deg: float = 2.0  # uniform in [-r, r], shared by both frames
    # the Gauss-Newton head starts from the previous pair's motion at run time (constant
    # velocity); training starts it from the GT previous motion, and from identity with this
    # probability, so that it also learns to converge from a cold start (a sequence's first pair)
    cold_start: float = 0.2
    held_out_returns: float = 0.2  # without depth_2/: share of LiDAR returns kept out of the input as target


def rigid_flow(depth: np.ndarray, K: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Optical flow of a static scene from frame 1 to frame 2: back-project with depth, move by
    inv(A) (A = frame 2's pose in frame 1), project. Returns (2,H,W) flow and (1,H,W) validity.

    Exact on the synthetic world (dense z-buffer); on real KITTI it is defined at LiDAR pixels.
    """
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = depth.astype(np.float64)
    X = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 0).reshape(3, -1)
    Ainv = np.linalg.inv(A)
    X2 = Ainv[:3, :3] @ X + Ainv[:3, 3:4]
    z2 = X2[2]
    ok = (z.reshape(-1) > 0) & (z2 > 0.1)
    z2 = np.where(ok, z2, 1.0)
    u2 = K[0, 0] * X2[0] / z2 + K[0, 2]
    v2 = K[1, 1] * X2[1] / z2 + K[1, 2]
    flow = np.stack([u2 - u.reshape(-1), v2 - v.reshape(-1)], 0)
    flow[:, ~ok] = 0.0
    return flow.reshape(2, h, w).astype(np.float32), ok.reshape(1, h, w).astype(np.float32)


def pose_vector(A: np.ndarray) -> np.ndarray:
    """4x4 -> (t, q) with q = (w, x, y, z), w >= 0."""
    return np.concatenate([A[:3, 3], rot_to_quat(A[:3, :3])]).astype(np.float32)


def mask_or_unknown(mask: np.ndarray | None, like: np.ndarray) -> np.ndarray:
    """(1,h,w) float32 of a 0/1 mask; -1 everywhere where there is none (nobody knows)."""
    return (mask if mask is not None else np.full(like.shape[1:], -1.0)).astype(np.float32)[None]


class FrameLoader:
    """Reads one frame of a sequence at the network resolution, through the runtime's preprocessor."""

    def __init__(self, seq: KittiSequence, cfg: D3LVOConfig, cache: str | Path | None = None):
        self.seq, self.cfg = seq, cfg
        h, w = seq.image(0).shape[:2]
        self.pre = FramePreprocessor.create(seq.calib, w, h, cfg.width, cfg.height, cfg.depth_input, cfg.max_depth)
        self.view: View = self.pre.view
        self.K = self.pre.K
        # a synthetic drive rendered without traffic has no motion_2/: nothing in it moves
        self.static_synthetic = drive_traffic(seq.root) == 0
        self.points = point_config(cfg.to_dict())
        self.cache = None if cache is None else Path(cache) / self._cache_key()

    def _cache_key(self) -> str:
        """Everything a cached frame depends on besides its own files: the sequence, the view, the
        depth input and the projection, and the solver's point selection."""
        v = self.view
        key = json.dumps([str(self.seq.root.resolve()), [v.src_width, v.src_height, v.top, v.left, v.crop_width,
                          v.crop_height, v.width, v.height], self.cfg.depth_input, self.cfg.max_depth,
                          np.round(self.pre.P, 9).tolist(), str(self.points)])
        return f"{self.seq.root.name}-{hashlib.sha256(key.encode()).hexdigest()[:16]}"

    def _cached(self, kind: str, i: int, make: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        """`make()` once per frame and kind, then from `cache` (an .npz named after the frame's scan
        and image sizes and times, so that a changed file is read again). Written atomically:
        loader workers and DDP ranks may fill the same cache."""
        if self.cache is None or not self.seq.scan_path(i).is_file():
            return make()
        stamp = "-".join(f"{st.st_size}-{st.st_mtime_ns}" for st in
                         (self.seq.scan_path(i).stat(), self.seq.image_path(i).stat()))
        f = self.cache / f"{self.seq.frame_names[i]}-{kind}-{stamp}.npz"
        if f.is_file():
            with np.load(f) as z:
                return dict(z)
        arrays = make()
        self.cache.mkdir(parents=True, exist_ok=True)
        tmp = f.with_name(f"{f.stem}.{os.getpid()}.tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, f)
        return arrays

    def rgb(self, i: int) -> np.ndarray:
        img = self.seq.image(i)
        if img.shape[:2] != (self.view.src_height, self.view.src_width):
            raise D3LVOInputError(self.seq.image_path(i), f"size {img.shape[1]}x{img.shape[0]} differs from frame 0")
        return self.pre.rgb(img)

    def depth_input(self, i: int, points: np.ndarray | None = None) -> np.ndarray:
        """The depth input of frame i from its whole scan (cached, where a cache is given), or
        from `points` (a share of it, never cached)."""
        if self.cfg.depth_input == "none":
            return self.pre.depth(None)
        if points is not None:
            return self.pre.depth(points)
        return self._cached("depth", i, lambda: {"depth": self.pre.depth(self.seq.scan(i))})["depth"]

    def _png(self, folder: str, i: int) -> np.ndarray | None:
        f = self.seq.root / folder / f"{self.seq.frame_names[i]}.png"
        if not f.is_file():
            return None
        a = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if a is None:
            raise D3LVOInputError(f, f"cannot be decoded as a {folder} PNG")
        return a

    def flow_target_map(self, i: int) -> np.ndarray | None:
        """Frame i's flow to frame i+1 at the network resolution, from `flow_2/` (KITTI flow PNG,
        source pixels): (3,h,w) flow u, v in network pixels and validity; None without it. The
        displacement is resampled, not the target position: nearest resampling picks a source
        pixel up to a pixel away from the network pixel's centre, which cancels in a displacement."""
        png = self._png("flow_2", i)
        if png is None:
            return None
        flow, valid = decode_kitti_flow(png)
        A = self.view.affine
        # nearest resampling as for depth: a target must not blend a car's pixel with the road's
        return np.stack([self.view.apply_depth(a.astype(np.float32))
                         for a in (A[0, 0] * flow[..., 0], A[1, 1] * flow[..., 1], valid)])

    def motion_mask(self, i: int) -> np.ndarray | None:
        """1 on pixels of things that move on their own; None where nobody knows (real KITTI). A
        synthetic drive rendered without traffic has no motion_2/: nothing in it moves."""
        return self._mask("motion_2", i)

    def shadow_mask(self, i: int) -> np.ndarray | None:
        """1 where a surface that stays put changes its shading by frame i+1 because a moving
        vehicle's shadow moves over it (shadow_2/): its appearance moves with the vehicle, so the
        solver must not trust it either. None where nobody knows (real KITTI, synthetic drives
        without shadow_2/)."""
        return self._mask("shadow_2", i)

    def _mask(self, folder: str, i: int) -> np.ndarray | None:
        """A 0/1 mask of `folder` at the network view; zeros for a drive where nothing moves."""
        m = self._png(folder, i)
        if m is None:
            return np.zeros((self.cfg.height, self.cfg.width), np.float32) if self.static_synthetic else None
        return self.view.apply_depth((m > 0).astype(np.float32))

    def solver_frame(self, i: int, depth: bool = False) -> SolverFrame:
        """Frame i as the point solver reads it (camera resolution, textured LiDAR points; with
        `depth`, its own LiDAR depth, for a solver that checks its restart against the scan)."""
        def make() -> dict[str, np.ndarray]:
            f = SolverFrame.of(self.seq.image(i), self.seq.scan(i), self.seq.calib.T_cam2_velo, self.seq.calib.K2,
                               self.points)
            return {"grey": f.grey, "points": f.points}

        a = self._cached("solver", i, make)
        if not depth:
            return SolverFrame(a["grey"], a["points"])
        grey, calib = a["grey"], self.seq.calib  # not cached: 1 ms
        return SolverFrame(a["grey"], a["points"], depth=sparse_depth(clean_scan(self.seq.scan(i)),
                                                                     calib.P_velo_to_image2, grey.shape[1], grey.shape[0]))

    def gt_depth(self, i: int) -> np.ndarray:
        f = self.seq.root / "depth_2" / f"{self.seq.frame_names[i]}.png"
        if not f.is_file():
            return np.zeros((self.cfg.height, self.cfg.width), np.float32)
        d = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if d is None:
            raise D3LVOInputError(f, "cannot be decoded as a depth PNG")
        return self.view.apply_depth(d.astype(np.float32) / 256.0)


class PairDataset(Dataset):
    def __init__(self, seq_dirs: list[str | Path], cfg: D3LVOConfig, augment: AugmentConfig | None = None,
                 seed: int = 0, solver: bool = False, cache: str | Path | None = None):
        """`solver`: each sample also carries the point solver's inputs (camera-resolution grey
        images and frame t-1's points), for a pose loss through the solver; the solver reads the
        camera's own images, so flips and rotations, which would have to be applied to them too,
        must be off. `cache`: a folder for each frame's projected depth and solver points
        (`FrameLoader`), so that later epochs read them instead of the scans."""
        if solver and augment is not None and (augment.flip > 0 or augment.rotation_deg > 0):
            raise ValueError("the solver's inputs are not augmented: flip and rotation_deg must be 0 with solver=True")
        self.cfg, self.augment, self.seed, self.solver = cfg, augment, seed, solver
        self.loaders: list[FrameLoader] = []
        self.items: list[tuple[int, int]] = []
        for d in seq_dirs:
            seq = KittiSequence.open(d)
            if seq.ground_truth is None:
                raise D3LVOInputError(d, "has no ground-truth poses (poses.txt or ../../poses/NN.txt) to train on")
            self.loaders.append(FrameLoader(seq, cfg, cache))
            self.items += [(len(self.loaders) - 1, i) for i in range(1, len(seq))]
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.items)

    def relative_pose(self, k: int, i: int) -> np.ndarray:
        """GT motion of the image_2 camera from frame i-1 to i."""
        loader = self.loaders[k]
        gt = loader.seq.ground_truth.poses
        return change_frame(relative(gt[i - 1], gt[i]), loader.seq.calib.T_cam2_cam0)

    def solver_inputs(self, idx: int) -> dict[str, torch.Tensor]:
        """The point solver's inputs for sample idx, unaugmented (evaluation; batch of one)."""
        k, i = self.items[idx]
        L = self.loaders[k]
        feeds = solver_feeds(L.solver_frame(i - 1), L.solver_frame(i, self.cfg.reads_scan), L.seq.calib.K2,
                             self.cfg.pt_capacity)
        return {n: torch.from_numpy(np.ascontiguousarray(a)) for n, a in feeds.items()}

    def identity_errors(self) -> tuple[float, float]:
        """Mean |t|_1 and |q - q_identity|^2 over all pairs: eq. 11's error terms for a network that
        predicts no motion. Cheap: poses only, no images."""
        v = np.stack([pose_vector(self.relative_pose(k, i)) for k, i in self.items]).astype(np.float64)
        return float(np.abs(v[:, :3]).sum(1).mean()), float(((v[:, 3:] - [1.0, 0, 0, 0]) ** 2).sum(1).mean())

    def __getitem__(self, idx: int) -> dict[str, torch.Tensor]:
        k, i = self.items[idx]
        L = self.loaders[k]
        rng = np.random.default_rng([self.seed, self.epoch, idx])
        imgs = [L.rgb(i - 1), L.rgb(i)]
        gts = [L.gt_depth(j) for j in (i - 1, i)]
        deps, rigid_depth = [], gts[0]  # the rigid-flow target wants depth wherever it can have it
        for n, j in enumerate((i - 1, i)):
            if np.any(gts[n] > 0):  # the renderer's z-buffer is the target; every return is input
                deps.append(L.depth_input(j))
                continue
            # real KITTI: each scan read once; a random share of its returns is the target only
            scan = L.seq.scan(j)
            out = rng.uniform(size=len(scan)) < (self.augment.held_out_returns if self.augment else 0.0)
            deps.append(L.depth_input(j, scan[~out]))
            gts[n] = sparse_depth(scan[out] if out.any() else scan, L.pre.P, self.cfg.width, self.cfg.height)
            if n == 0:
                rigid_depth = sparse_depth(scan, L.pre.P, self.cfg.width, self.cfg.height) if out.any() else gts[0]
        gts.append(rigid_depth)
        target = L.flow_target_map(i - 1)  # (3,h,w) or None
        moving, shadow = L.motion_mask(i - 1), L.shadow_mask(i - 1)
        maps = [] if target is None else [target[0], target[1], target[2]]
        masks = [m for m in (moving, shadow) if m is not None]
        maps += masks  # moving, then shadow: both at the end of maps
        A = self.relative_pose(k, i)
        A0 = self.relative_pose(k, i - 1) if i >= 2 else np.eye(4)
        if self.augment is not None and rng.uniform() < self.augment.cold_start:
            A0 = np.eye(4)
        if self.augment is not None:
            a = self.augment
            cx, cy = float(L.K[0, 2]), float(L.K[1, 2])
            if rng.uniform() < a.flip:
                imgs, deps, gts = flip_images(*imgs), flip_images(*deps), flip_images(*gts)
                maps = flip_images(*maps)
                if target is not None:  # the flow mirrors with the image
                    maps[0] = -maps[0]
                A, A0 = flip_pose(A), flip_pose(A0)
                cx = self.cfg.width - 1 - cx  # the principal point mirrors too
            if a.rotation_deg > 0:
                ang = float(rng.uniform(-a.rotation_deg, a.rotation_deg))
                centre = (cx, cy)
                imgs, deps2 = rotate_images(imgs, deps + gts + maps, ang, centre)
                deps, gts, maps = deps2[:2], deps2[2:5], deps2[5:]
                if target is not None:  # and turns with it (both frames turn alike: no shift)
                    R = cv2.getRotationMatrix2D(centre, ang, 1.0)
                    du, dv = maps[0], maps[1]
                    maps[0], maps[1] = R[0, 0] * du + R[0, 1] * dv, R[1, 0] * du + R[1, 1] * dv
                A, A0 = roll_pose(A, ang), roll_pose(A0, ang)
            if a.brightness > 0:
                f = float(rng.uniform(1 - a.brightness, 1 + a.brightness))
                imgs = [np.clip(im * f, 0.0, 1.0) for im in imgs]
        else:
            cx, cy = float(L.K[0, 2]), float(L.K[1, 2])
        K = L.K.copy()
        K[0, 2], K[1, 2] = cx, cy
        if target is None:
            flow, valid = rigid_flow(gts[2], K, A)
        else:
            valid = (maps[2] > 0.5).astype(np.float32)[None]
            flow = (np.stack([maps[0], maps[1]]) * valid).astype(np.float32)
        t = lambda x: torch.from_numpy(np.ascontiguousarray(x))  # noqa: E731
        solver = {}
        if self.solver:
            feeds = solver_feeds(L.solver_frame(i - 1), L.solver_frame(i), L.seq.calib.K2, self.cfg.pt_capacity)
            solver = {n: t(a[0]) for n, a in feeds.items()}  # the loader stacks the batch
        return {
            **solver,
            "rgb1": t(imgs[0]).permute(2, 0, 1), "rgb2": t(imgs[1]).permute(2, 0, 1),
            "depth1": t(deps[0])[None], "depth2": t(deps[1])[None],
            "gt_depth1": t(gts[0])[None], "gt_depth2": t(gts[1])[None],
            "pose": t(pose_vector(A)), "matrix": t(A.astype(np.float32)), "init": t(A0.astype(np.float32)),
            "K": t(np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float32)),
            "flow": t(flow), "flow_valid": t(valid),
            # 1 on moving vehicles, 0 elsewhere, -1 where the sequence has no motion masks; the same
            # for moving shadows on surfaces that stay put (`shadow_mask`)
            "moving": t(mask_or_unknown(maps[len(maps) - len(masks)] if moving is not None else None, flow)),
            "shadow": t(mask_or_unknown(maps[-1] if shadow is not None else None, flow)),
        }
