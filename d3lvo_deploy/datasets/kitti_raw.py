"""KITTI raw drives (`<date>/<date>_drive_NNNN_sync/`): image_02/data, velodyne_points/data,
the date folder's calib_cam_to_cam.txt and calib_velo_to_cam.txt, and OXTS ground truth.

Poses are written in rectified cam0, as for KITTI odometry: Tr = R_rect_00 [R|T] (velo -> cam0,
rectified) and P2 = P_rect_02, the same matrices the odometry benchmark's calib.txt holds.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..calib import Calib
from ..errors import D3LVOInputError
from ..geometry import make_se3, se3_inv
from ..poses import Trajectory
from ..sequence import _check_contiguous, read_image, read_scan
from .base import SensorSequence, check_increasing

EARTH_RADIUS = 6378137.0  # m, the devkit's `er`


def is_kitti_raw(path: Path) -> bool:
    return (path / "image_02" / "data").is_dir() and (path / "velodyne_points" / "data").is_dir()


def read_calib_values(path: Path) -> dict[str, np.ndarray]:
    """KITTI raw calib text: `KEY: numbers` per line; lines that are not numbers (calib_time) are skipped."""
    if not path.is_file():
        raise D3LVOInputError(path, "calibration file not found (a KITTI raw drive keeps it in the date folder "
                                    "or the drive folder)")
    out = {}
    for line in path.read_text(errors="replace").splitlines():
        key, _, rest = line.partition(":")
        try:
            out[key.strip()] = np.array([float(v) for v in rest.split()])
        except ValueError:
            continue
    return out


def _entry(path: Path, values: dict, key: str, size: int) -> np.ndarray:
    v = values.get(key)
    if v is None or v.size != size:
        got = "missing" if v is None else f"{v.size} numbers"
        raise D3LVOInputError(path, f"{key} is {got}, expected {size} numbers")
    return v


def _find_calib(drive: Path, name: str) -> Path:
    for d in (drive, drive.parent):
        if (d / name).is_file():
            return d / name
    return drive.parent / name


def raw_calib(drive: Path) -> tuple[Calib, np.ndarray | None]:
    """(Calib with P2 = P_rect_02 and Tr = R_rect_00 [R|T]; T_velo_imu, or None without calib_imu_to_velo)."""
    c2c_path, v2c_path = _find_calib(drive, "calib_cam_to_cam.txt"), _find_calib(drive, "calib_velo_to_cam.txt")
    c2c, v2c = read_calib_values(c2c_path), read_calib_values(v2c_path)
    P2 = _entry(c2c_path, c2c, "P_rect_02", 12).reshape(3, 4)
    R_rect = make_se3(_entry(c2c_path, c2c, "R_rect_00", 9).reshape(3, 3), np.zeros(3))
    T_cam_velo = make_se3(_entry(v2c_path, v2c, "R", 9).reshape(3, 3), _entry(v2c_path, v2c, "T", 3))
    imu_path = _find_calib(drive, "calib_imu_to_velo.txt")
    T_velo_imu = None
    if imu_path.is_file():
        i2v = read_calib_values(imu_path)
        T_velo_imu = make_se3(_entry(imu_path, i2v, "R", 9).reshape(3, 3), _entry(imu_path, i2v, "T", 3))
    return Calib(P2=P2, Tr=R_rect @ T_cam_velo), T_velo_imu


def read_raw_times(path: Path, n: int) -> np.ndarray:
    """`YYYY-MM-DD HH:MM:SS.fffffffff` lines -> seconds since the first (nanoseconds kept)."""
    if not path.is_file():
        return np.arange(n) * 0.1
    stamps = []
    for k, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        day, _, frac = line.strip().partition(".")
        try:
            whole = datetime.strptime(day, "%Y-%m-%d %H:%M:%S").timestamp()
            stamps.append((whole, float("0." + frac) if frac else 0.0))
        except ValueError:
            raise D3LVOInputError(path, f"line {k}: {line.strip()[:40]!r} is not a 'YYYY-MM-DD HH:MM:SS.f' time") from None
    if len(stamps) != n:
        raise D3LVOInputError(path, f"{len(stamps)} timestamps for {n} frames")
    t = np.array([w - stamps[0][0] + f for w, f in stamps])
    return check_increasing(path, t)


def oxts_poses(records: np.ndarray) -> np.ndarray:
    """(N,>=6) OXTS rows (lat, lon, alt, roll, pitch, yaw, ...) -> (N,4,4) IMU poses relative to
    the first, as the KITTI devkit's convertOxtsToPose.m computes them (Mercator, scale from the
    first latitude, R = Rz(yaw) Ry(pitch) Rx(roll))."""
    lat, lon, alt, roll, pitch, yaw = (records[:, k] for k in range(6))
    scale = np.cos(lat[0] * np.pi / 180.0)
    t = np.stack([scale * lon * np.pi * EARTH_RADIUS / 180.0,
                  scale * EARTH_RADIUS * np.log(np.tan((90.0 + lat) * np.pi / 360.0)), alt], -1)
    c, s = np.cos, np.sin
    one, zero = np.ones_like(roll), np.zeros_like(roll)
    Rx = np.stack([one, zero, zero, zero, c(roll), -s(roll), zero, s(roll), c(roll)], -1).reshape(-1, 3, 3)
    Ry = np.stack([c(pitch), zero, s(pitch), zero, one, zero, -s(pitch), zero, c(pitch)], -1).reshape(-1, 3, 3)
    Rz = np.stack([c(yaw), -s(yaw), zero, s(yaw), c(yaw), zero, zero, zero, one], -1).reshape(-1, 3, 3)
    T = make_se3(Rz @ Ry @ Rx, t)
    return se3_inv(T[0]) @ T


def _read_oxts(folder: Path, names: list[str]) -> np.ndarray:
    rows = []
    for n in names:
        p = folder / f"{n}.txt"
        if not p.is_file():
            raise D3LVOInputError(p, "OXTS record missing (one per camera frame in a _sync drive)")
        try:
            v = [float(x) for x in p.read_text().split()]
        except ValueError:
            raise D3LVOInputError(p, "OXTS record is not a row of numbers") from None
        if len(v) < 6:
            raise D3LVOInputError(p, f"{len(v)} numbers, an OXTS record has 30 (lat, lon, alt, roll, pitch, yaw, ...)")
        rows.append(v[:6])
    return np.asarray(rows, dtype=np.float64)


@dataclass
class KittiRawSequence(SensorSequence):
    format_name: ClassVar[str] = "kitti-raw"
    @classmethod
    def open(cls, drive: str | Path) -> "KittiRawSequence":
        drive = Path(drive).resolve()  # the calib files may be in its parent, the date folder
        if not is_kitti_raw(drive):
            raise D3LVOInputError(drive, "not a KITTI raw drive (needs image_02/data/ and velodyne_points/data/)")
        img_dir, velo_dir = drive / "image_02" / "data", drive / "velodyne_points" / "data"
        images = sorted(p.stem for p in img_dir.glob("*.png"))
        scans = sorted(p.stem for p in velo_dir.glob("*.bin"))
        if not images:
            raise D3LVOInputError(img_dir, "holds no .png images")
        if images != scans:
            lonely = sorted(set(images) - set(scans))[:3]
            extra = sorted(set(scans) - set(images))[:3]
            raise D3LVOInputError(drive, f"{len(images)} images but {len(scans)} scans; frames without a scan: {lonely}, "
                                         f"scans without an image: {extra} (a _sync drive has one of each per frame; "
                                         "an ..._extract drive's are not paired)")
        _check_contiguous(drive, images)
        calib, T_velo_imu = raw_calib(drive)
        stamps = drive / "image_02" / "timestamps.txt"
        if not stamps.is_file():
            warnings.warn(f"{stamps}: missing; the frames are taken as 0.1 s apart (KITTI's 10 Hz)", stacklevel=2)
        times = read_raw_times(stamps, len(images))
        gt, gt_path = None, None
        oxts = drive / "oxts" / "data"
        if oxts.is_dir() and T_velo_imu is None:
            warnings.warn(f"{drive}: oxts/ is there but calib_imu_to_velo.txt is not (in the drive or its date "
                          "folder), which places the IMU: the run is not scored", stacklevel=2)
        if oxts.is_dir() and T_velo_imu is not None:
            T_cam_imu = calib.Tr @ T_velo_imu  # IMU -> rectified cam0
            imu = oxts_poses(_read_oxts(oxts, images))
            gt = Trajectory.from_poses(T_cam_imu @ imu @ se3_inv(T_cam_imu), times)
            gt_path = oxts
        return cls(root=drive, calib=calib, frame_names=images, times=times,
                   frame_label="cam0 (rectified left grey camera, KITTI's convention)", gt=gt, gt_path=gt_path)

    def image(self, i: int) -> np.ndarray:
        return read_image(self.root / "image_02" / "data" / f"{self.frame_names[i]}.png")

    def scan(self, i: int) -> np.ndarray:
        return read_scan(self.root / "velodyne_points" / "data" / f"{self.frame_names[i]}.bin")
