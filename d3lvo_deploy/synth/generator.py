"""`d3lvo synth`: write a synthetic sequence in the KITTI odometry layout.

Output: image_2/*.png, velodyne/*.bin, calib.txt, times.txt, poses.txt (cam0, first pose identity)
and depth_2/*.png, the renderer's z-buffer as KITTI depth-completion PNGs (uint16, metres * 256,
0 = sky), usable as dense ground truth. With traffic, also motion_2/*.png (255 where a pixel
sees a vehicle that moves between this frame and the next), flow_2/*.png, the true optical
flow of image_2 from each frame to the next (ego motion and vehicle motion), in KITTI's flow
format (uint16 u, v as 64 x flow + 2^15, and a valid flag; none for the last frame), and
shadow_2/*.png (255 where a surface that stays put changes its shading by the next frame because a
moving vehicle's shadow moves over it; none for the last frame). Each frame is written as soon as it is rendered and is a
pure function of (seed, frame), so an interrupted run resumes where it stopped with identical data.
"""

from __future__ import annotations

import json
import math
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
from .sensors import Exposure, LidarConfig, Scene, cam2_pose, render_camera, scan_lidar, velo_pose
from .shading import noise_texture
from .traffic import Vehicle, plan_traffic, point_motion, shadow_change, world_at
from .world import build_path, build_world

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
    traffic: float = 0.0  # moving vehicles per 100 m of driven road
    sensor_effects: bool = False  # exposure changes, vignetting, shot noise, dark/far LiDAR dropout
    # keep vehicles whose schedule runs into the camera's own car (`traffic.meets_ego`): how the
    # bundled model's training and validation drives were rendered (scripts/train_default.sh)
    ego_collisions: bool = False

    def meta(self) -> dict:
        """synth.json: the settings, leaving out the traffic and sensor keys at their defaults, so
        that a static drive's file names only what shapes it (and static folders stay resumable);
        with traffic, `ego_collisions` either way (`rendered_settings`)."""
        d = {"generator_version": GENERATOR_VERSION, **asdict(self)}
        for k in ("traffic", "sensor_effects"):
            if not d[k]:
                del d[k]
        if not self.traffic:  # no vehicles to keep or leave out
            del d["ego_collisions"]
        return d

    def as_written(self) -> dict:
        """`meta` as synth.json reads back (tuples as lists): what a render's file is compared with."""
        return json.loads(json.dumps(self.meta()))


def rendered_settings(folder: str | Path) -> dict | None:
    """The settings in a render's synth.json; None where it is missing, unreadable or not settings.
    A render with traffic whose file does not name `ego_collisions` kept every vehicle: read as
    true, so that resuming or reusing it asks for that."""
    try:
        settings = json.loads((Path(folder) / "synth.json").read_text())
    except (OSError, ValueError):  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        return None
    if not isinstance(settings, dict):
        return None
    if settings.get("traffic") and "ego_collisions" not in settings:
        settings["ego_collisions"] = True
    return settings


def drive_traffic(folder: str | Path) -> float | None:
    """Moving vehicles per 100 m a synthetic drive was rendered with (its synth.json); None for a
    folder `generate` did not write, such as real data."""
    meta = Path(folder) / "synth.json"
    return float(json.loads(meta.read_text()).get("traffic", 0) or 0) if meta.is_file() else None


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


def _frame_done(out: Path, name: str, cfg: SynthConfig, last: bool) -> bool:
    files = [out / "image_2" / f"{name}.png", out / "velodyne" / f"{name}.bin"]
    if cfg.write_depth:
        files.append(out / "depth_2" / f"{name}.png")
    if cfg.traffic:
        files += [out / "motion_2" / f"{name}.png"] + ([] if last else [out / d / f"{name}.png" for d in ("flow_2", "shadow_2")])
    return all(f.is_file() and f.stat().st_size > 0 for f in files)


def _renders(out: Path, cfg: SynthConfig, i: int, resume: bool) -> bool:
    """Whether `generate` renders frame i: always, unless a resumed folder holds it whole."""
    return not (resume and _frame_done(out, f"{i:06d}", cfg, i == cfg.frames - 1))


def frames_to_render(out: Path, cfg: SynthConfig, resume: bool = True) -> int:
    """How many of the frames `generate` renders (a resumed folder keeps the ones it holds), so
    that the command says what it did rather than the frames asked for."""
    return sum(_renders(Path(out), cfg, i, resume) for i in range(cfg.frames))


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


def sensor_exposures(cfg: SynthConfig) -> list[Exposure]:
    """Per-frame camera effects from the seed: auto-exposure gain drifting as a random walk in log
    space (within 0.6x-1.5x) with occasional jumps (entering shade, a tunnel, sun glare), one
    vignetting strength and shot noise for the drive."""
    rng = np.random.default_rng([cfg.seed, 4])
    steps = rng.normal(0.0, 0.03, cfg.frames) + (rng.uniform(size=cfg.frames) < 0.03) * rng.normal(0.0, 0.2, cfg.frames)
    log_gain = np.clip(np.cumsum(steps), np.log(0.6), np.log(1.5))
    vignette, shot = float(rng.uniform(0.2, 0.45)), float(rng.uniform(0.3, 1.0))
    return [Exposure(float(np.exp(g)), vignette, shot) for g in log_gain]


def _moves(v: Vehicle, i: int) -> bool:
    """Whether vehicle v moves between frame i and the next (the previous, at the last frame)."""
    j = i + 1 if i + 1 < len(v.poses) else i - 1
    return bool(np.linalg.norm(v.poses[j][:3, 3] - v.poses[i][:3, 3]) > 0.01)


def true_flow(depth: np.ndarray, owner: np.ndarray, vehicles: list[Vehicle], K: np.ndarray, T_w_c0: np.ndarray,
              T_w_c1: np.ndarray, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """(H,W,2) image_2 flow from this frame to the next and its validity: every pixel's surface
    point moved as its owner moves (static: not at all), projected with the next camera pose."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    X = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) * depth[..., None]
    Xw = X.reshape(-1, 3) @ T_w_c0[:3, :3].T + T_w_c0[:3, 3]
    Xw = point_motion(vehicles, owner.reshape(-1), Xw, frame, frame + 1)
    T = np.linalg.inv(T_w_c1)
    Xc = Xw @ T[:3, :3].T + T[:3, 3]
    valid = (depth.reshape(-1) > 0) & (Xc[:, 2] > 0.1)
    z = np.where(valid, Xc[:, 2], 1.0)
    flow = np.stack([K[0, 0] * Xc[:, 0] / z + K[0, 2] - u.reshape(-1), K[1, 1] * Xc[:, 1] / z + K[1, 2] - v.reshape(-1)], 1)
    flow[~valid] = 0.0
    return flow.reshape(h, w, 2), valid.reshape(h, w)


def encode_kitti_flow(flow: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """KITTI flow PNG channels (u, v, valid), as BGR for cv2.imwrite: uint16 64 x flow + 2^15."""
    enc = np.clip(np.round(flow * 64.0 + 32768.0), 0, 65535).astype(np.uint16)
    return np.dstack([valid.astype(np.uint16), enc[..., 1], enc[..., 0]])


def decode_kitti_flow(png_bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of encode_kitti_flow for an image read with cv2.IMREAD_UNCHANGED."""
    flow = (np.dstack([png_bgr[..., 2], png_bgr[..., 1]]).astype(np.float64) - 32768.0) / 64.0
    return flow, png_bgr[..., 0] > 0


def check_config(cfg: SynthConfig) -> None:
    """The settings' own errors, before anything is rendered or a progress bar drawn."""
    if cfg.frames < 2:
        raise D3LVOInputError(None, "--frames must be at least 2")
    if cfg.frames > MAX_FRAMES:  # the motion and its buffers are made for every frame up front
        raise D3LVOInputError(None, f"--frames {cfg.frames} is too many: at most {MAX_FRAMES} (render a longer drive "
                                    "as several)")
    if cfg.width < 64 or cfg.height < 32:
        raise D3LVOInputError(None, f"--size {cfg.width}x{cfg.height} is too small")
    if cfg.width > 4096 or cfg.height > 4096:  # a frame's float buffers would take gigabytes
        raise D3LVOInputError(None, f"--size {cfg.width}x{cfg.height} is too large: at most 4096 a side")
    if not (math.isfinite(cfg.traffic) and cfg.traffic >= 0):
        raise D3LVOInputError(None, f"--traffic must be 0 or more vehicles per 100 m, not {cfg.traffic}")
    if cfg.seed < 0:
        raise D3LVOInputError(None, f"--seed must be 0 or more, not {cfg.seed}")
    if cfg.motion_start < 0 or (cfg.motion_start and cfg.motion_from is None):
        raise D3LVOInputError(None, "--motion-start is the first frame of --motion-from's trajectory to replay: "
                                    "0 or more, and only with --motion-from")


FRAME_FOLDERS = ("image_2", "velodyne", "depth_2", "motion_2", "flow_2", "shadow_2")
# what a render writes beside its frames: in a folder without synth.json they are someone else's
SEQUENCE_FILES = ("poses.txt", "calib.txt", "times.txt")
MAX_FRAMES = 100_000  # KITTI's longest sequence has 4,661


def _frame_folders(cfg: SynthConfig) -> tuple[str, ...]:
    """The folders a render with these settings writes."""
    return ("image_2", "velodyne") + (("depth_2",) if cfg.write_depth else ()) + \
        (("motion_2", "flow_2", "shadow_2") if cfg.traffic else ())


def _drop_stale(out: Path, cfg: SynthConfig) -> None:
    """What an earlier render left that this one will not write again (--overwrite): frames
    beyond its count, and whole target folders its settings do not write (an earlier drive's
    flow, motion masks or depth, which training would otherwise read beside the new images)."""
    keep = _frame_folders(cfg)
    for d in FRAME_FOLDERS:
        for f in (out / d).glob("*") if (out / d).is_dir() else ():
            if f.stem.isdigit() and (d not in keep or int(f.stem) >= cfg.frames):
                f.unlink()
        if d not in keep and (out / d).is_dir() and not any((out / d).iterdir()):
            (out / d).rmdir()


def check_output(out: Path, cfg: SynthConfig, resume: bool = True) -> None:
    """What `out` may hold: nothing, or this command's render of these settings (resumed), or of
    any settings with --overwrite (`resume` False). Frames it did not render (no synth.json: a
    real KITTI sequence?) are refused either way: their images would stay beside new poses and
    calibration."""
    out = Path(out)
    meta_path = out / "synth.json"
    if out.exists() and not out.is_dir():
        raise D3LVOInputError(out, "is a file: --out names the folder to render the sequence into")
    if not meta_path.exists():
        if str(out) in ("", ".") and any(out.iterdir()):  # an empty --out: the working directory, the user's files
            raise D3LVOInputError(None, "--out is the working directory, which holds other files: give a folder to "
                                        "render into")
        if any((out / d).is_dir() and any((out / d).iterdir()) for d in FRAME_FOLDERS):
            raise D3LVOInputError(out, "holds frames that d3lvo synth did not render (no synth.json): use an empty or "
                                       "new --out")
        theirs = [f for f in SEQUENCE_FILES if (out / f).exists()]
        if theirs:
            raise D3LVOInputError(out, f"holds {', '.join(theirs)} that d3lvo synth did not write (no synth.json): "
                                       "use an empty or new --out")
        return
    if not meta_path.is_file():
        raise D3LVOInputError(meta_path, "is not a file, where d3lvo synth keeps a render's settings: use another --out")
    if resume:
        old, new = rendered_settings(out), cfg.as_written()
        if old is None:
            raise D3LVOInputError(meta_path, "is not the settings file d3lvo synth writes (unreadable or damaged): "
                                             "use another --out, or --overwrite to render the folder again")
        if old != new:
            # the key that says most: a static render against one with traffic differs in both
            # `traffic` and `ego_collisions`, which only follows from it
            keys = sorted(set(old) | set(new), key=lambda k: (k == "ego_collisions", k))
            key = next(k for k in keys if old.get(k) != new.get(k))
            shown = lambda v: "unset" if v is None else repr(v)  # noqa: E731  (a static render has no traffic)
            raise D3LVOInputError(out, f"holds a synthetic sequence made with other settings ({key} "
                                       f"{shown(old.get(key))} there, {shown(new.get(key))} asked); use another "
                                       "--out, or --overwrite to render it again")


def generate(out: str | Path, cfg: SynthConfig, progress: Callable[[int], None] | None = None,
             resume: bool = True) -> Path:
    out = Path(out)
    check_config(cfg)
    check_output(out, cfg, resume)
    meta = cfg.meta()
    meta_path = out / "synth.json"
    poses = make_poses(cfg)  # reads --motion-from: a bad file is refused before any folder is made
    try:
        for d in _frame_folders(cfg):
            (out / d).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise D3LVOInputError(out, f"cannot create the output folder ({e.strerror})") from None
    if not resume and meta_path.is_file():  # --overwrite of a folder this command rendered
        _drop_stale(out, cfg)
    calib = kitti_calib(cfg.width, cfg.height)
    meta_path.write_text(json.dumps(meta, indent=2))
    (out / "calib.txt").write_text(calib.to_text())
    (out / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(cfg.frames)))
    write_poses(out / "poses.txt", poses)

    scene = make_scene(poses, cfg.seed)
    vehicles = plan_traffic(build_path(poses), scene.style, poses, cfg.traffic, np.random.default_rng([cfg.seed, 3]),
                            clear_ego=not cfg.ego_collisions) if cfg.traffic else []
    exposures = sensor_exposures(cfg) if cfg.sensor_effects else [None] * cfg.frames
    K = calib.K2
    for i in range(cfg.frames):
        name = f"{i:06d}"
        if _renders(out, cfg, i, resume):
            rng = np.random.default_rng([cfg.seed, 2, i])
            frame_scene, owner = scene, None
            if vehicles:
                world, owner = world_at(scene.world, vehicles, i)
                frame_scene = Scene(RayCaster(world["vertices"], world["faces"]), world, scene.style, scene.tex,
                                    scene.sun)
            hits: dict = {}
            img, depth = render_camera(frame_scene, K, cam2_pose(poses[i], calib), cfg.width, cfg.height, rng,
                                       exposure=exposures[i], hits=hits)
            scan = scan_lidar(frame_scene, velo_pose(poses[i], calib), cfg.lidar, rng,
                              weak_dropout=0.3 if cfg.sensor_effects else 0.0)
            if vehicles:
                pix_owner = np.where(hits["prim"] >= 0, owner[np.maximum(hits["prim"], 0)], -1)
                moving = np.array([_moves(v, i) for v in vehicles] + [False])  # index -1: static
                _write_atomic(out / "motion_2" / f"{name}.png", _png(np.where(moving[pix_owner], 255, 0).astype(np.uint8)))
                if i + 1 < cfg.frames:
                    flow, valid = true_flow(depth, pix_owner, vehicles, K, cam2_pose(poses[i], calib),
                                            cam2_pose(poses[i + 1], calib), i)
                    _write_atomic(out / "flow_2" / f"{name}.png", _png(encode_kitti_flow(flow, valid)))
                    shade = shadow_change(hits, moving[pix_owner], vehicles, moving[:-1], scene.sun, i, scene.caster)
                    _write_atomic(out / "shadow_2" / f"{name}.png", _png(np.where(shade, 255, 0).astype(np.uint8)))
            _write_atomic(out / "velodyne" / f"{name}.bin", scan.tobytes())
            if cfg.write_depth:
                d16 = np.clip(np.round(depth * 256.0), 0, 65535).astype(np.uint16)
                _write_atomic(out / "depth_2" / f"{name}.png", _png(d16))
            _write_atomic(out / "image_2" / f"{name}.png", _png(cv2.cvtColor(img, cv2.COLOR_RGB2BGR)))
        if progress is not None:
            progress(i + 1)
    return out
