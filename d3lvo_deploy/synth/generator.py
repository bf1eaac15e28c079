"""`d3lvo synth`: write a synthetic sequence in the KITTI odometry layout.

Output: image_2/*.png, velodyne/*.bin, calib.txt, times.txt, poses.txt (cam0, first pose identity)
and depth_2/*.png, the renderer's z-buffer as KITTI depth-completion PNGs (uint16, metres * 256,
0 = sky), usable as dense ground truth. Each frame is written as soon as it is rendered and is a
pure function of (seed, frame), so an interrupted run resumes where it stopped with identical data.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..calib import Calib
from ..errors import D3LVOInputError
from ..poses import write_poses
from .motion import DriveConfig, replay_gt, synthetic_drive
from .raycast import RayCaster
from .sensors import LidarConfig, Scene, cam2_pose, render_camera, scan_lidar, velo_pose
from .shading import noise_texture
from .world import build_world

GENERATOR_VERSION = 1

# Real KITTI calibration (raw drive 2011_09_26, rectified; Tr = R_rect_00 @ Tr_velo_to_cam), image 1242x375.
KITTI_P2 = np.array([[721.5377, 0.0, 609.5593, 44.85728],
                     [0.0, 721.5377, 172.854, 0.2163791],
                     [0.0, 0.0, 1.0, 0.002745884]])
KITTI_TR = np.array([[2.347736981471e-04, -9.999441545438e-01, -1.056347781105e-02, -2.796816941295e-03],
                     [1.044940741659e-02, 1.056535364138e-02, -9.998895741176e-01, -7.510879138296e-02],
                     [9.999453885620e-01, 1.243653783865e-04, 1.045130299567e-02, -2.721327964059e-01],
                     [0.0, 0.0, 0.0, 1.0]])
KITTI_SIZE = (1242, 375)


def kitti_calib(width: int = 1241, height: int = 376) -> Calib:
    """The real calib, intrinsics scaled to another image size (the baseline b is unchanged)."""
    S = np.diag([width / KITTI_SIZE[0], height / KITTI_SIZE[1], 1.0])
    P2 = S @ KITTI_P2
    P0 = np.hstack([P2[:, :3], np.zeros((3, 1))])
    return Calib(P2=P2, Tr=KITTI_TR.copy(), P0=P0)


@dataclass
class SynthConfig:
    frames: int = 100
    seed: int = 0
    width: int = 1241
    height: int = 376
    motion_from: str | None = None  # a KITTI GT file to replay
    motion_start: int = 0
    write_depth: bool = True
    lidar: LidarConfig = field(default_factory=LidarConfig)
    drive: DriveConfig = field(default_factory=DriveConfig)


def make_poses(cfg: SynthConfig) -> np.ndarray:
    if cfg.motion_from:
        return replay_gt(cfg.motion_from, cfg.frames, cfg.motion_start)
    return synthetic_drive(cfg.frames, cfg.seed, cfg.drive)


def make_scene(poses: np.ndarray, seed: int) -> Scene:
    world, _, style = build_world(poses, seed)
    rng = np.random.default_rng([seed, 1])
    elev = np.radians(rng.uniform(30, 60))
    az = rng.uniform(0, 2 * np.pi)
    sun = np.array([np.cos(elev) * np.sin(az), -np.sin(elev), np.cos(elev) * np.cos(az)])
    return Scene(RayCaster(world["vertices"], world["faces"]), world, style, noise_texture(seed), sun)


def _frame_done(out: Path, name: str, cfg: SynthConfig) -> bool:
    files = [out / "image_2" / f"{name}.png", out / "velodyne" / f"{name}.bin"]
    if cfg.write_depth:
        files.append(out / "depth_2" / f"{name}.png")
    return all(f.is_file() and f.stat().st_size > 0 for f in files)


def _write_atomic(path: Path, data: bytes) -> None:
    """Write to a temporary name and rename, so a killed run never leaves a half-written frame."""
    tmp = path.with_name(path.name + ".part")
    tmp.write_bytes(data)
    tmp.replace(path)


def _png(array: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", array)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def generate(out: str | Path, cfg: SynthConfig, progress: Callable[[int], None] | None = None,
             resume: bool = True) -> Path:
    out = Path(out)
    if cfg.frames < 2:
        raise D3LVOInputError(None, "--frames must be at least 2")
    if cfg.width < 64 or cfg.height < 32:
        raise D3LVOInputError(None, f"--size {cfg.width}x{cfg.height} is too small")
    try:
        for d in ("image_2", "velodyne") + (("depth_2",) if cfg.write_depth else ()):
            (out / d).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise D3LVOInputError(out, f"cannot create the output folder ({e.strerror})") from None
    meta = {"generator_version": GENERATOR_VERSION, **asdict(cfg)}
    meta_path = out / "synth.json"
    if meta_path.is_file() and resume:
        old = json.loads(meta_path.read_text())
        if old != json.loads(json.dumps(meta)):
            raise D3LVOInputError(out, "holds a synthetic sequence made with other settings; use another --out")
    poses = make_poses(cfg)
    calib = kitti_calib(cfg.width, cfg.height)
    meta_path.write_text(json.dumps(meta, indent=2))
    (out / "calib.txt").write_text(calib.to_text())
    (out / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(cfg.frames)))
    write_poses(out / "poses.txt", poses)

    scene = make_scene(poses, cfg.seed)
    K = calib.K2
    for i in range(cfg.frames):
        name = f"{i:06d}"
        if not (resume and _frame_done(out, name, cfg)):
            rng = np.random.default_rng([cfg.seed, 2, i])
            img, depth = render_camera(scene, K, cam2_pose(poses[i], calib), cfg.width, cfg.height, rng)
            scan = scan_lidar(scene, velo_pose(poses[i], calib), cfg.lidar, rng)
            _write_atomic(out / "velodyne" / f"{name}.bin", scan.tobytes())
            if cfg.write_depth:
                d16 = np.clip(np.round(depth * 256.0), 0, 65535).astype(np.uint16)
                _write_atomic(out / "depth_2" / f"{name}.png", _png(d16))
            _write_atomic(out / "image_2" / f"{name}.png", _png(cv2.cvtColor(img, cv2.COLOR_RGB2BGR)))
        if progress is not None:
            progress(i + 1)
    return out
