"""Every input format behind one call, `open_sequence(path)`, the format guessed from the path
(as KISS-ICP's dataloaders do) or forced with `fmt`:

| format     | what the path is                                                         |
|------------|--------------------------------------------------------------------------|
| kitti      | a KITTI odometry sequence: image_2/*.png, velodyne/*.bin, calib.txt       |
| kitti-raw  | a KITTI raw drive (..._sync): image_02/data, velodyne_points/data, OXTS  |
| rosbag     | a ROS 1 .bag, or a ROS 2 bag (folder with metadata.yaml, .db3 or .mcap)  |
| folder     | images/ + scans/ (.pcd .ply .bin .npy) with the same names, calib.txt    |
"""

from __future__ import annotations

from pathlib import Path

from ..errors import D3LVOInputError
from ..sequence import KittiSequence
from .base import SensorSequence
from .folder import FolderSequence, is_folder
from .kitti_raw import KittiRawSequence, is_kitti_raw
from .rosbag import BagOptions, BagSequence, is_bag

FORMATS = ("kitti", "kitti-raw", "rosbag", "folder")
Recording = KittiSequence | SensorSequence  # what the pipeline runs on

__all__ = ["FORMATS", "Recording", "BagOptions", "BagSequence", "FolderSequence", "KittiRawSequence", "SensorSequence",
           "guess_format", "open_sequence"]


def guess_format(path: str | Path) -> str:
    path = Path(path)
    if not path.exists():
        raise D3LVOInputError(path, "not found")
    if is_bag(path):
        return "rosbag"
    if path.is_dir():
        if (path / "image_2").is_dir() and (path / "velodyne").is_dir() and any((path / "velodyne").glob("*.bin")):
            return "kitti"
        if is_kitti_raw(path):
            return "kitti-raw"
        if is_folder(path):
            return "folder"
        if (path / "image_2").is_dir() and (path / "velodyne").is_dir():
            return "kitti"  # without frames: KittiSequence says what is missing
    raise D3LVOInputError(path, "is none of the formats D3LVO reads: a KITTI odometry sequence (image_2/, "
                                "velodyne/), a KITTI raw drive (image_02/data/, velodyne_points/data/), a ROS bag "
                                "(.bag, .mcap, .db3, or a folder with metadata.yaml), or a folder of images/ and "
                                "scans/ with calib.txt; --format names one")


def open_sequence(path: str | Path, fmt: str = "auto", gt: str | Path | None = None, calib: str | Path | None = None,
                  bag: BagOptions | None = None) -> Recording:
    """The recording at `path` as a sequence the pipeline runs on (KittiSequence or a SensorSequence).
    `gt`: a trajectory file to score against; `calib`: a calibration file for folders and bags."""
    path = Path(path)
    fmt = fmt.lower() if isinstance(fmt, str) else fmt  # as --pose-format: KITTI is kitti
    fmt = guess_format(path) if fmt in ("auto", None) else fmt
    if fmt not in FORMATS:
        raise D3LVOInputError(None, f"--format must be auto or one of {', '.join(FORMATS)}, not {fmt!r}")
    if calib is not None and fmt in ("kitti", "kitti-raw"):
        raise D3LVOInputError(calib, f"--calib is for bags and folders; a {fmt} sequence brings its own calibration")
    if bag is not None and fmt != "rosbag":  # a bag's options on another format would be ignored without a word
        given = [f"--{k.replace('_', '-')}" for k in ("image_topic", "cloud_topic", "info_topic")
                 if getattr(bag, k) is not None] + (["--max-dt"] if bag.max_dt != BagOptions.max_dt else [])
        if given:
            raise D3LVOInputError(path, f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} for ROS bags; "
                                        f"this is a {fmt} recording")
    if fmt == "kitti":
        return KittiSequence.open(path, gt=gt)
    if fmt == "folder":
        return FolderSequence.open(path, calib=calib, gt=gt)
    if fmt == "kitti-raw":
        seq = KittiRawSequence.open(path)
    else:
        opts = bag if bag is not None else BagOptions()
        if calib is not None:
            opts = BagOptions(**{**opts.__dict__, "calib": Path(calib)})
        seq = BagSequence.open(path, opts)
    if gt is not None:
        seq.attach_ground_truth(gt)
    return seq
