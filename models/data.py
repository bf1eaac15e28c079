"""Training pairs from KITTI-format sequences (real KITTI or `d3lvo synth` output).

A sample is frames (t-1, t) at the network resolution: RGB in [0,1], the depth input the config
asks for (sparse LiDAR, IP-Basic dense, or nothing), the renderer's dense depth where the
sequence has `depth_2/` (else zeros), and the GT relative pose of the image_2 camera.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.geometry import change_frame, relative, rot_to_quat
from d3lvo_deploy.frames import FramePreprocessor
from d3lvo_deploy.projection import View, sparse_depth
from d3lvo_deploy.sequence import KittiSequence

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


class FrameLoader:
    """Reads one frame of a sequence at the network resolution, through the runtime's preprocessor."""

    def __init__(self, seq: KittiSequence, cfg: D3LVOConfig):
        self.seq, self.cfg = seq, cfg
        h, w = seq.image(0).shape[:2]
        self.pre = FramePreprocessor.create(seq.calib, w, h, cfg.width, cfg.height, cfg.depth_input, cfg.max_depth)
        self.view: View = self.pre.view
        self.K = self.pre.K

    def rgb(self, i: int) -> np.ndarray:
        img = self.seq.image(i)
        if img.shape[:2] != (self.view.src_height, self.view.src_width):
            raise D3LVOInputError(self.seq.image_path(i), f"size {img.shape[1]}x{img.shape[0]} differs from frame 0")
        return self.pre.rgb(img)

    def depth_input(self, i: int) -> np.ndarray:
        return self.pre.depth(None if self.cfg.depth_input == "none" else self.seq.scan(i))

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
                 seed: int = 0):
        self.cfg, self.augment, self.seed = cfg, augment, seed
        self.loaders: list[FrameLoader] = []
        self.items: list[tuple[int, int]] = []
        for d in seq_dirs:
            seq = KittiSequence.open(d)
            if seq.ground_truth is None:
                raise D3LVOInputError(d, "has no ground-truth poses (poses.txt or ../../poses/NN.txt) to train on")
            self.loaders.append(FrameLoader(seq, cfg))
            self.items += [(len(self.loaders) - 1, i) for i in range(1, len(seq))]
        self.epoch = 0

    def __len__(self) -> int:
        return len(self.items)

    def relative_pose(self, k: int, i: int) -> np.ndarray:
        """GT motion of the image_2 camera from frame i-1 to i."""
        loader = self.loaders[k]
        gt = loader.seq.ground_truth.poses
        return change_frame(relative(gt[i - 1], gt[i]), loader.seq.calib.T_cam2_cam0)

    def identity_errors(self) -> tuple[float, float]:
        """Mean |t|_1 and |q - q_identity|^2 over all pairs: eq. 11's error terms for a network that
        predicts no motion. Cheap: poses only, no images."""
        v = np.stack([pose_vector(self.relative_pose(k, i)) for k, i in self.items]).astype(np.float64)
        return float(np.abs(v[:, :3]).sum(1).mean()), float(((v[:, 3:] - [1.0, 0, 0, 0]) ** 2).sum(1).mean())

    def __getitem__(self, idx: int) -> dict[str, torch.Tensor]:
        k, i = self.items[idx]
        L = self.loaders[k]
        imgs = [L.rgb(i - 1), L.rgb(i)]
        deps = [L.depth_input(i - 1), L.depth_input(i)]
        # depth targets (completion L1, flow target): the dense z-buffer where the data has one
        # (synthetic depth_2/), else the LiDAR returns themselves (real KITTI)
        gts = [L.gt_depth(j) for j in (i - 1, i)]
        gts = [g if np.any(g > 0) else sparse_depth(L.seq.scan(j), L.pre.P, self.cfg.width, self.cfg.height)
               for g, j in zip(gts, (i - 1, i))]
        gts.append(gts[0])
        A = self.relative_pose(k, i)
        A0 = self.relative_pose(k, i - 1) if i >= 2 else np.eye(4)
        rng = np.random.default_rng([self.seed, self.epoch, idx])
        if self.augment is not None and rng.uniform() < self.augment.cold_start:
            A0 = np.eye(4)
        if self.augment is not None:
            a = self.augment
            cx, cy = float(L.K[0, 2]), float(L.K[1, 2])
            if rng.uniform() < a.flip:
                imgs, deps, gts = flip_images(*imgs), flip_images(*deps), flip_images(*gts)
                A, A0 = flip_pose(A), flip_pose(A0)
                cx = self.cfg.width - 1 - cx  # the principal point mirrors too
            if a.rotation_deg > 0:
                ang = float(rng.uniform(-a.rotation_deg, a.rotation_deg))
                centre = (cx, cy)
                imgs, deps2 = rotate_images(imgs, deps + gts, ang, centre)
                deps, gts = deps2[:2], deps2[2:]
                A, A0 = roll_pose(A, ang), roll_pose(A0, ang)
            if a.brightness > 0:
                f = float(rng.uniform(1 - a.brightness, 1 + a.brightness))
                imgs = [np.clip(im * f, 0.0, 1.0) for im in imgs]
        else:
            cx, cy = float(L.K[0, 2]), float(L.K[1, 2])
        K = L.K.copy()
        K[0, 2], K[1, 2] = cx, cy
        flow, valid = rigid_flow(gts[2], K, A)
        t = lambda x: torch.from_numpy(np.ascontiguousarray(x))  # noqa: E731
        return {
            "rgb1": t(imgs[0]).permute(2, 0, 1), "rgb2": t(imgs[1]).permute(2, 0, 1),
            "depth1": t(deps[0])[None], "depth2": t(deps[1])[None],
            "gt_depth1": t(gts[0])[None], "gt_depth2": t(gts[1])[None],
            "pose": t(pose_vector(A)), "matrix": t(A.astype(np.float32)), "init": t(A0.astype(np.float32)),
            "K": t(np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.float32)),
            "flow": t(flow), "flow_valid": t(valid),
        }
