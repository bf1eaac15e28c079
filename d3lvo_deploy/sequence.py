"""KITTI odometry sequence folders: image_2/*.png, velodyne/*.bin, calib.txt, times.txt, poses.

Ground truth is looked for, in order: an explicit path, `poses.txt` inside the sequence (what
`d3lvo synth` writes), and `<root>/poses/NN.txt` beside `<root>/sequences/NN` (the KITTI layout).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import ClassVar
from pathlib import Path

import cv2
import numpy as np

from .calib import Calib, parse_calib
from .errors import D3LVOInputError
from .poses import Trajectory, read_poses


def read_scan(path: str | Path) -> np.ndarray:
    """(N,4) float32 x, y, z, reflectance; raises on a truncated file."""
    path = Path(path)
    if not path.is_file():
        raise D3LVOInputError(path, "LiDAR scan not found")
    size = path.stat().st_size
    if size % 16:
        raise D3LVOInputError(path, f"{size} bytes is not a whole number of float32 x,y,z,r points (truncated?)")
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


def read_image(path: str | Path) -> np.ndarray:
    """(H,W,3) uint8 RGB."""
    path = Path(path)
    if not path.is_file():
        raise D3LVOInputError(path, "image not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise D3LVOInputError(path, "cannot be decoded as an image (corrupt or not a PNG?)")
    if img.dtype != np.uint8:
        img = (img.astype(np.float32) * (255.0 / np.iinfo(img.dtype).max)).round().astype(np.uint8) \
            if np.issubdtype(img.dtype, np.integer) else np.clip(img * 255.0, 0, 255).astype(np.uint8)
    if img.ndim == 2 or img.shape[2] == 1:
        # the message names the folder, not the frame, so it is shown once per sequence
        warnings.warn(f"{path.parent}: greyscale images (KITTI's image_0/image_1 are grey; D3LVO reads the colour "
                      "camera image_2): the grey value is used for all three channels", GreyscaleWarning, stacklevel=2)
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)


class GreyscaleWarning(UserWarning):
    """image_2 holds single-channel images: usually the greyscale cameras' folder was given."""


@dataclass
class KittiSequence:
    frame_label: ClassVar[str] = "cam0 (rectified left grey camera, KITTI's convention)"
    format_name: ClassVar[str] = "kitti"  # `d3lvo run --format`
    root: Path
    calib: Calib
    frame_names: list[str]
    times: np.ndarray
    gt_path: Path | None = None
    _gt: Trajectory | None = field(default=None, repr=False)

    @classmethod
    def open(cls, root: str | Path, gt: str | Path | None = None) -> "KittiSequence":
        root = Path(root)
        if not root.is_dir():
            raise D3LVOInputError(root, "sequence folder not found")
        img_dir, velo_dir = root / "image_2", root / "velodyne"
        for d in (img_dir, velo_dir):
            if not d.is_dir():
                raise D3LVOInputError(d, "missing (a KITTI sequence needs image_2/ and velodyne/)")
        images = sorted(p.stem for p in img_dir.glob("*.png"))
        scans = sorted(p.stem for p in velo_dir.glob("*.bin"))
        if not images:
            raise D3LVOInputError(img_dir, "holds no .png images")
        if images != scans:
            only_img = sorted(set(images) - set(scans))[:3]
            only_scan = sorted(set(scans) - set(images))[:3]
            raise D3LVOInputError(
                root,
                f"{len(images)} images but {len(scans)} scans; frames without a scan: {only_img}, "
                f"scans without an image: {only_scan}",
            )
        _check_contiguous(root, images)
        calib = parse_calib(root / "calib.txt")
        times = _read_times(root / "times.txt", len(images))
        gt_path = Path(gt) if gt is not None else _find_gt(root)
        return cls(root, calib, images, times, gt_path)

    @classmethod
    def from_kitti_root(cls, kitti_root: str | Path, sequence: str) -> "KittiSequence":
        """`<kitti_root>/sequences/<NN>`, with ground truth from `<kitti_root>/poses/<NN>.txt` if present."""
        return cls.open(Path(kitti_root) / "sequences" / sequence)

    def __len__(self) -> int:
        return len(self.frame_names)

    @property
    def calib_path(self) -> Path:
        return self.root / "calib.txt"

    def image_path(self, i: int) -> Path:
        return self.root / "image_2" / f"{self.frame_names[i]}.png"

    def scan_path(self, i: int) -> Path:
        return self.root / "velodyne" / f"{self.frame_names[i]}.bin"

    def image(self, i: int) -> np.ndarray:
        return read_image(self.image_path(i))

    def scan(self, i: int) -> np.ndarray:
        return read_scan(self.scan_path(i))

    @property
    def ground_truth(self) -> Trajectory | None:
        if self.gt_path is None:
            return None
        if self._gt is None:
            gt = read_poses(self.gt_path)
            if len(gt) != len(self):
                raise D3LVOInputError(self.gt_path, f"{len(gt)} poses for a sequence of {len(self)} frames "
                                                    "(--gt names the file to score against)")
            self._gt = gt
        return self._gt


# file names that are frame counts rather than time stamps
FRAME_NUMBERS_BELOW = 10_000_000


def _check_contiguous(root: Path, names: list[str]) -> None:
    """KITTI frames are numbered 000000..N-1; a gap would silently pair non-consecutive frames."""
    if not all(n.isdigit() for n in names):
        return
    ids = np.array([int(n) for n in names])
    if ids[0] >= FRAME_NUMBERS_BELOW:  # stamps as names (a recorder's ns or ms): no count to check
        return
    check_no_gap(root, names, ids)


def check_no_gap(root: Path, names: list[str], ids: np.ndarray) -> None:
    """One error at the first step of the frame count `ids` (of `names`) that is not 1."""
    gaps = np.nonzero(np.diff(ids) != 1)[0]
    if len(gaps):
        g = gaps[0]
        raise D3LVOInputError(root, f"frame numbers jump from {names[g]} to {names[g + 1]} (missing frame?)")


# a recording whose frames are further apart than this (s, by the median) has times in another unit
SLOWEST_FRAME_STEP = 10.0


def _read_times(path: Path, n: int) -> np.ndarray:
    if path.is_dir():
        raise D3LVOInputError(path, "is a folder; times.txt holds one timestamp per frame in seconds")
    if not path.is_file():
        return np.arange(n) * 0.1
    stamps = []
    for k, line in enumerate(path.read_text().splitlines(), 1):
        words = line.split()
        if not words:
            continue
        word = words[0]
        try:
            stamps.append(float(word))
        except ValueError:
            raise D3LVOInputError(path, f"line {k}: {word[:40]!r} is not a time in seconds") from None
        if len(stamps) > 1 and not stamps[-1] > stamps[-2]:
            raise D3LVOInputError(path, f"line {k}: {stamps[-1]:g} s does not come after {stamps[-2]:g} s "
                                        "(timestamps must increase)")
    if len(stamps) != n:
        raise D3LVOInputError(path, f"{len(stamps)} timestamps for {n} frames")
    step = float(np.median(np.diff(stamps))) if n > 1 else 0.0
    if step > SLOWEST_FRAME_STEP:
        warnings.warn(f"{path}: its frames are {step:g} apart (median): times are read as seconds (milliseconds or "
                      "nanoseconds?); --realtime paces by them, the motion guard and TUM poses use them", stacklevel=3)
    return np.array(stamps, dtype=np.float64)


def _find_gt(root: Path) -> Path | None:
    inside = root / "poses.txt"
    if inside.is_file():
        return inside
    beside = root.parent.parent / "poses" / f"{root.name}.txt"
    return beside if beside.is_file() else None
