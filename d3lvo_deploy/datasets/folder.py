"""A plain folder: one subfolder of images, one of LiDAR scans (.pcd, .ply, .bin or .npy) with
the same file names, and a calibration file; optional times.txt and poses.txt.

Readers are the formats' own libraries (pypcd4 for PCD, plyfile for PLY, the `[sensors]`
extra), not hand-written parsers: PCD alone has ASCII, binary and LZF-compressed bodies.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..calib import parse_calib
from ..errors import D3LVOInputError
from ..sequence import FRAME_NUMBERS_BELOW, _read_times, check_no_gap, read_image, read_scan
from .base import SensorSequence, as_scan

IMAGE_DIRS = ("image_2", "images", "image", "camera", "rgb", "img")
SCAN_DIRS = ("velodyne", "scans", "lidar", "points", "pointclouds", "pcd", "clouds")
IMAGE_EXTS = (".png", ".jpg", ".jpeg")
SCAN_EXTS = (".pcd", ".ply", ".bin", ".npy")
CALIB_NAMES = ("calib.txt", "calib.yaml", "calibration.txt")
INTENSITY_NAMES = ("intensity", "reflectance", "i", "remission")


def read_pcd(path: Path) -> np.ndarray:
    from ..extras import require

    require("pypcd4", what=f"reading {path.name}")
    from pypcd4 import PointCloud

    try:
        pc = PointCloud.from_path(path)
    except Exception as e:  # noqa: BLE001 - the library's own error types vary by body kind
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""  # a validator's report runs to many lines
        raise D3LVOInputError(path, f"cannot be read as a PCD file ({type(e).__name__}: {first[:120]})") from None
    fields = list(pc.fields)
    if not {"x", "y", "z"} <= set(fields):
        raise D3LVOInputError(path, f"PCD fields {fields} lack x, y, z")
    inten = next((f for f in INTENSITY_NAMES if f in fields), None)
    arr = pc.numpy(("x", "y", "z") + ((inten,) if inten else ()))
    return as_scan(path, arr[:, :3], arr[:, 3] if inten else None)


def read_ply(path: Path) -> np.ndarray:
    from ..extras import require

    require("plyfile", what=f"reading {path.name}")
    from plyfile import PlyData

    try:
        vertex = PlyData.read(str(path))["vertex"]
    except Exception as e:  # noqa: BLE001
        raise D3LVOInputError(path, f"cannot be read as a PLY file with a 'vertex' element ({e})") from None
    names = vertex.data.dtype.names
    if not {"x", "y", "z"} <= set(names):
        raise D3LVOInputError(path, f"PLY vertex properties {list(names)} lack x, y, z")
    inten = next((f for f in INTENSITY_NAMES if f in names), None)
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], -1)
    return as_scan(path, xyz, vertex[inten] if inten else None)


def read_npy(path: Path) -> np.ndarray:
    try:
        with open(path, "rb") as fh:
            if fh.read(6) != b"\x93NUMPY":  # else np.load takes it for a pickle and says so
                raise D3LVOInputError(path, "is not a .npy file (no NumPy header; np.save writes one)")
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as e:
        raise D3LVOInputError(path, f"cannot be read as a .npy array ({e})") from None
    if arr.ndim != 2 or arr.shape[1] not in (3, 4):
        raise D3LVOInputError(path, f"array of shape {arr.shape}; a scan is (N,3) x,y,z or (N,4) x,y,z,intensity")
    return as_scan(path, arr[:, :3], arr[:, 3] if arr.shape[1] == 4 else None)


READERS = {".pcd": read_pcd, ".ply": read_ply, ".bin": read_scan, ".npy": read_npy}


def read_any_scan(path: str | Path) -> np.ndarray:
    """(N,4) float32 from any of the scan formats, chosen by extension."""
    path = Path(path)
    if not path.is_file():
        raise D3LVOInputError(path, "LiDAR scan not found")
    reader = READERS.get(path.suffix.lower())
    if reader is None:
        raise D3LVOInputError(path, f"unknown scan format; D3LVO reads {', '.join(SCAN_EXTS)}")
    return reader(path)


def _counted(stems: list[str]) -> list[re.Match] | None:
    """The names as one prefix and a whole number each (frame_8, frame_9, ..., or 8, 9, 10), or
    None: other names (a decimal time stamp, 1630000000.15) keep the text order."""
    parts = [re.fullmatch(r"(.*?)(\d+)", s) for s in stems]
    if not all(parts) or len({m.group(1) for m in parts}) != 1 or parts[0].group(1).endswith("."):
        return None
    return parts


def frame_order(files: list[Path]) -> list[Path]:
    """frame_9 before frame_10: counted names by their number (as text, unpadded names would run
    frame 10 before frame 9); any other names in text order."""
    files = sorted(files)
    counted = _counted([p.stem for p in files])
    return files if counted is None else [p for _, p in sorted(zip((int(m.group(2)) for m in counted), files))]


def _pick(root: Path, names: tuple[str, ...], exts: tuple[str, ...]) -> tuple[Path, list[Path]] | None:
    for n in names:
        d = root / n
        if d.is_dir():
            files = frame_order([p for p in d.iterdir() if p.suffix.lower() in exts])
            if files:
                return d, files
    return None


def _check_numbered(root: Path, names: list[str]) -> None:
    """Frame counts in the names (frame_8, frame_9, ... or 000008, 000009, ...): a gap in them
    would pair frames that are not consecutive, as in a KITTI folder. Names that count something
    else (time stamps, milliseconds from the start: fewer than half their steps are 1) are not
    checked."""
    counted = _counted(names)
    if counted is None or len(names) < 2:
        return
    ids = np.array([int(m.group(2)) for m in counted])
    steps = np.diff(ids)
    if ids[0] >= FRAME_NUMBERS_BELOW or np.mean(steps == 1) < 0.5:
        return
    check_no_gap(root, names, ids)


def is_folder(path: Path) -> bool:
    return path.is_dir() and _pick(path, IMAGE_DIRS, IMAGE_EXTS) is not None \
        and _pick(path, SCAN_DIRS, SCAN_EXTS) is not None


@dataclass
class FolderSequence(SensorSequence):
    format_name: ClassVar[str] = "folder"
    image_files: list[Path] | None = None
    scan_files: list[Path] | None = None

    @classmethod
    def open(cls, root: str | Path, calib: str | Path | None = None, gt: str | Path | None = None) -> "FolderSequence":
        root = Path(root)
        if not root.is_dir():
            raise D3LVOInputError(root, "folder not found")
        images = _pick(root, IMAGE_DIRS, IMAGE_EXTS)
        scans = _pick(root, SCAN_DIRS, SCAN_EXTS)
        if images is None:
            raise D3LVOInputError(root, f"no image folder ({', '.join(IMAGE_DIRS)}) with {'/'.join(IMAGE_EXTS)} files")
        if scans is None:
            raise D3LVOInputError(root, f"no scan folder ({', '.join(SCAN_DIRS)}) with {'/'.join(SCAN_EXTS)} files")
        (img_dir, img_files), (scan_dir, scan_files) = images, scans
        kinds = {p.suffix.lower() for p in scan_files}
        if len(kinds) > 1:
            raise D3LVOInputError(scan_dir, f"holds scans of several formats {sorted(kinds)}; keep one")
        by_stem = {p.stem: p for p in scan_files}
        names = [p.stem for p in img_files]
        missing = [n for n in names if n not in by_stem]
        if missing or len(scan_files) != len(img_files):
            extra = sorted(set(by_stem) - set(names))[:3]
            raise D3LVOInputError(root, f"{len(img_files)} images in {img_dir.name}/ but {len(scan_files)} scans in "
                                        f"{scan_dir.name}/; images without a scan: {missing[:3]}, scans without an "
                                        f"image: {extra}")
        _check_numbered(root, names)
        if calib is None:
            calib = next((root / n for n in CALIB_NAMES if (root / n).is_file()), root / "calib.txt")
        cal = parse_calib(calib)
        times = _read_times(root / "times.txt", len(names))
        label = (f"the camera of the calibration's K ({cal.keys[1]} takes the LiDAR there)" if cal.keys[0] == "K"
                 else f"cam0 (the frame of the calibration's {cal.keys[0]} and {cal.keys[1]})")
        seq = cls(root=root, calib=cal, frame_names=names, times=times, frame_label=label, image_files=img_files,
                  scan_files=[by_stem[n] for n in names], calib_path=Path(calib))
        gt = gt if gt is not None else (root / "poses.txt" if (root / "poses.txt").is_file() else None)
        if gt is not None:
            seq.attach_ground_truth(gt)
        return seq

    def image(self, i: int) -> np.ndarray:
        return read_image(self.image_files[i])

    def scan(self, i: int) -> np.ndarray:
        return read_any_scan(self.scan_files[i])
