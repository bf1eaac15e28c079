"""The synthetic KITTI rig: colour camera image_2 and an HDL-64E-like LiDAR, one ray engine for both."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..calib import Calib
from .raycast import RayCaster
from .shading import albedo, sky
from .world import StreetStyle


@dataclass(frozen=True)
class LidarConfig:
    """HDL-64E: two blocks of 32 lasers (+2..-8.33 deg at 1/3 deg, -8.83..-24.8 deg at ~1/2 deg)."""

    azimuth_res_deg: float = 0.09
    max_range: float = 120.0
    min_range: float = 2.5  # returns off the car's own roof are filtered in KITTI too
    noise_m: float = 0.01
    dropout: float = 0.05

    def elevations(self) -> np.ndarray:
        return np.radians(np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.8, 32)]))


@dataclass
class Scene:
    caster: RayCaster
    world: dict[str, np.ndarray]
    style: StreetStyle
    tex: np.ndarray
    sun: np.ndarray  # unit vector towards the sun, world frame


def _surface(scene: Scene, origins: np.ndarray, dirs: np.ndarray):
    """Cast rays; return hits plus per-ray uv, camera-facing unit normal and hit points."""
    h = scene.caster.cast(origins, dirs)
    w = scene.world
    ok = h.hit
    prim = h.prim[ok]
    f = w["faces"][prim]
    b1, b2 = h.u[ok, None], h.v[ok, None]
    uv = (1 - b1 - b2) * w["uv"][f[:, 0]] + b1 * w["uv"][f[:, 1]] + b2 * w["uv"][f[:, 2]]
    n = h.normal[ok].astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    d = dirs[ok] if dirs.ndim == 2 else dirs
    flip = (n * d).sum(1) > 0
    n[flip] *= -1
    o = origins[ok] if np.ndim(origins) == 2 and len(origins) == len(dirs) else origins
    pts = o + h.t[ok, None] * d
    return h, ok, prim, uv, n, pts


@dataclass(frozen=True)
class Exposure:
    """What a real camera adds to the scene's radiance in one frame: auto-exposure gain, lens
    vignetting (1 - strength r^2, r = 1 at the image corner) and photon shot noise (variance
    `shot` x the signal in 8-bit units) on top of the read noise."""

    gain: float = 1.0
    vignette: float = 0.0
    shot: float = 0.0


def render_camera(scene: Scene, K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int,
                  rng: np.random.Generator, noise_sigma: float = 2.0, exposure: Exposure | None = None,
                  hits: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(H,W,3) uint8 RGB image and (H,W) float32 z-depth (0 where the ray saw sky). `hits`, when
    given, receives each pixel's triangle ("prim", -1 for sky) and, for `traffic.shadow_change`,
    where its shadow ray starts ("shadow_origin", (H*W,3) world, NaN for sky) and how much sun its
    surface faces ("lit", (H*W,), 0 where a shadow cannot change its shading)."""
    jj, ii = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    d_cam = np.stack([(jj - K[0, 2]) / K[0, 0], (ii - K[1, 2]) / K[1, 1], np.ones_like(jj)], -1).reshape(-1, 3)
    R, c = T_world_cam[:3, :3], T_world_cam[:3, 3]
    dirs = d_cam @ R.T  # z component 1 in camera frame, so t is z-depth
    h, ok, prim, uv, n, pts = _surface(scene, c, dirs)
    w = scene.world
    ray_len = np.linalg.norm(dirs[ok], axis=1)
    cos = np.abs((n * dirs[ok]).sum(1)) / ray_len
    footprint = h.t[ok] * ray_len / K[0, 0] / np.maximum(cos, 0.15)
    alb = albedo(w["material"][prim], w["colour"][prim], w["variant"][prim], uv, footprint, scene.tex, scene.style)
    lit = np.clip((n * scene.sun).sum(1), 0.0, 1.0)
    shadow = scene.caster.occluded(pts + n * 0.02, np.broadcast_to(scene.sun, pts.shape))
    light = 0.5 + 0.75 * lit * (~shadow)
    img = np.empty((width * height, 3), dtype=np.float32)
    img[ok] = alb * light[:, None]
    img[~ok] = sky(dirs[~ok], scene.tex)
    if exposure is None:
        img = img * 255.0 + rng.normal(0.0, noise_sigma, img.shape)
    else:
        r2 = (((jj - width / 2) / (width / 2)) ** 2 + ((ii - height / 2) / (height / 2)) ** 2).reshape(-1, 1) / 2
        img = img * (255.0 * exposure.gain) * (1.0 - exposure.vignette * r2)
        sigma = np.sqrt(noise_sigma ** 2 + exposure.shot * np.clip(img, 0.0, 255.0))
        img = img + rng.normal(0.0, 1.0, img.shape) * sigma
    if hits is not None:
        hits["prim"] = h.prim.reshape(height, width)
        hits["shadow_origin"] = np.full((width * height, 3), np.nan)
        hits["shadow_origin"][ok] = pts + n * 0.02
        hits["lit"] = np.zeros(width * height)
        hits["lit"][ok] = lit
    depth = np.where(ok, h.t, 0.0).astype(np.float32).reshape(height, width)
    return np.clip(img, 0, 255).astype(np.uint8).reshape(height, width, 3), depth


def scan_lidar(scene: Scene, T_world_velo: np.ndarray, cfg: LidarConfig, rng: np.random.Generator,
               weak_dropout: float = 0.0) -> np.ndarray:
    """(N,4) float32 points in the LiDAR frame (x fwd, y left, z up) with reflectance in [0,1].
    `weak_dropout`: the most extra dropout of weak returns, reached by black surfaces and at
    `max_range` (each half of it), as a real sensor loses dark and far returns first."""
    el = cfg.elevations()
    az = np.radians(np.arange(0.0, 360.0, cfg.azimuth_res_deg))
    E, A = np.meshgrid(el, az, indexing="ij")
    d_velo = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    R, c = T_world_velo[:3, :3], T_world_velo[:3, 3]
    h, ok, prim, uv, n, pts = _surface(scene, c, d_velo @ R.T)
    w = scene.world
    rng_m = h.t[ok] + rng.normal(0.0, cfg.noise_m, ok.sum()) if cfg.noise_m > 0 else h.t[ok]
    keep = (rng_m > cfg.min_range) & (rng_m < cfg.max_range) & (rng.uniform(size=len(rng_m)) >= cfg.dropout)
    alb = albedo(w["material"][prim], w["colour"][prim], w["variant"][prim], uv, np.full(len(prim), 1.0),
                 scene.tex, scene.style)
    cos = np.abs((n * (d_velo[ok] @ R.T)).sum(1))
    refl = np.clip(alb.mean(1) * (0.3 + 0.7 * cos), 0.0, 1.0)
    if weak_dropout > 0:
        weak = 0.5 * (1.0 - refl) ** 2 + 0.5 * (rng_m / cfg.max_range) ** 2
        keep &= rng.uniform(size=len(rng_m)) >= weak_dropout * weak
    xyz = d_velo[ok] * rng_m[:, None]
    return np.concatenate([xyz, refl[:, None]], 1)[keep].astype(np.float32)


def cam2_pose(T_world_cam0: np.ndarray, calib: Calib) -> np.ndarray:
    return T_world_cam0 @ calib.T_cam0_cam2


def velo_pose(T_world_cam0: np.ndarray, calib: Calib) -> np.ndarray:
    return T_world_cam0 @ calib.Tr
