"""Vehicle motion for the synthetic world: a random but plausible drive, or a replayed KITTI GT.

Poses are camera-0 poses in the KITTI convention (x right, y down, z forward), first pose identity,
sampled at 10 Hz.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import D3LVOInputError
from ..geometry import make_se3, relative
from ..poses import read_poses

DT = 0.1


@dataclass(frozen=True)
class DriveConfig:
    max_speed: float = 12.0  # m/s (KITTI urban/residential drives at 5-14 m/s)
    accel: float = 1.5  # m/s^2
    decel: float = 3.0
    turn_speed: float = 4.5
    turn_radius: float = 14.0
    stop_probability: float = 0.15


def _rot_y(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(yaw), np.ones_like(yaw)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _rot_x(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _rot_z(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def synthetic_drive(frames: int, seed: int, cfg: DriveConfig = DriveConfig()) -> np.ndarray:
    """(frames,4,4) poses: cruising, gentle curves, 90-degree turns and stops, rate-limited."""
    rng = np.random.default_rng(seed)
    sub = 10  # integrate at 100 Hz, sample at 10 Hz
    n = frames * sub
    dt = DT / sub
    speed = float(rng.uniform(4.0, 9.0))
    yaw = 0.0
    x = z = 0.0
    kappa = 0.0
    xs, zs, yaws, speeds = (np.empty(n) for _ in range(4))
    kind, v_target, k_target, remaining = "cruise", speed, 0.0, 3.0
    heading_goal = None
    for i in range(n):
        if remaining <= 0 and (heading_goal is None):
            r = rng.uniform()
            if r < cfg.stop_probability:
                kind, v_target, k_target, remaining = "stop", 0.0, 0.0, float(rng.uniform(6.0, 10.0))
            elif r < cfg.stop_probability + 0.2:
                kind, v_target, remaining = "turn", cfg.turn_speed, 30.0
                sign = rng.choice([-1.0, 1.0])
                k_target = sign / cfg.turn_radius
                heading_goal = yaw + sign * np.pi / 2
            elif r < cfg.stop_probability + 0.5:
                kind, v_target, remaining = "curve", float(rng.uniform(5.0, cfg.max_speed)), float(rng.uniform(3, 8))
                k_target = float(rng.uniform(1 / 150, 1 / 50)) * rng.choice([-1.0, 1.0])
            else:
                kind, v_target, k_target, remaining = "cruise", float(rng.uniform(6.0, cfg.max_speed)), 0.0, float(rng.uniform(4, 12))
        if kind == "turn" and heading_goal is not None:
            # approach slowly, turn until the heading reaches the goal, then straighten
            if speed > cfg.turn_speed + 0.5:
                k_cmd = 0.0
            else:
                left = heading_goal - yaw
                k_cmd = k_target if abs(left) > 0.15 else k_target * abs(left) / 0.15
                if abs(left) < 0.01 or np.sign(left) != np.sign(k_target):
                    heading_goal, remaining = None, 0.0
                    kind, v_target, k_cmd = "cruise", float(rng.uniform(6.0, cfg.max_speed)), 0.0
                    remaining = float(rng.uniform(4, 10))
        else:
            k_cmd = k_target
        if kind == "stop" and speed < 0.05:
            speed = 0.0
        a = cfg.accel if v_target > speed else -cfg.decel
        speed = float(np.clip(speed + a * dt, min(speed, v_target) if a < 0 else 0, max(speed, v_target)))
        kappa += np.clip(k_cmd - kappa, -0.02 * dt * 10, 0.02 * dt * 10)
        yaw += speed * kappa * dt
        x += speed * np.sin(yaw) * dt
        z += speed * np.cos(yaw) * dt
        remaining -= dt
        if kind == "stop" and speed == 0.0 and remaining > 2.5:
            remaining = min(remaining, float(rng.uniform(1.0, 2.5)))
        xs[i], zs[i], yaws[i], speeds[i] = x, z, yaw, speed
    idx = np.arange(0, n, sub)
    xs, zs, yaws = xs[idx] - xs[0], zs[idx] - zs[0], yaws[idx] - yaws[0]
    # small suspension pitch/roll and a gentle height profile
    t = np.arange(frames) * DT
    pitch = np.radians(0.3) * np.sin(2 * np.pi * t / rng.uniform(3, 6) + rng.uniform(0, 6))
    roll = np.radians(0.2) * np.sin(2 * np.pi * t / rng.uniform(3, 6) + rng.uniform(0, 6))
    y = 0.03 * np.sin(2 * np.pi * t / rng.uniform(4, 8))
    R = _rot_y(yaws) @ _rot_x(pitch) @ _rot_z(roll)
    poses = make_se3(R, np.stack([xs, y - y[0], zs], -1))
    return relative(poses[0], poses)


MAX_STEP_M = 10.0  # per 0.1 s frame: 360 km/h


def replay_gt(path: str | Path, frames: int, start: int = 0) -> np.ndarray:
    """Frames [start, start+frames) of a real KITTI GT file, re-based so the first pose is identity."""
    traj = read_poses(path)
    if start < 0 or start + frames > len(traj):
        raise D3LVOInputError(path, f"has {len(traj)} poses; frames {start}..{start + frames - 1} requested")
    poses = traj.poses[start : start + frames]
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    if len(steps) and steps.max() > MAX_STEP_M:  # the world is built along the path: km-long steps exhaust memory
        i = start + int(steps.argmax())
        raise D3LVOInputError(path, f"moves {steps.max():.1f} m between frames {i} and {i + 1} (lines {i + 1} and "
                                    f"{i + 2}): the synthesizer renders a frame every 0.1 s, and more than "
                                    f"{MAX_STEP_M:.0f} m per frame ({MAX_STEP_M * 36:.0f} km/h) is no drive (poses "
                                    "in millimetres, or every n-th pose?)")
    return relative(poses[0], poses)
