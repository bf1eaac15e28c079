"""What the runtime reads from any recording: frame i's RGB image and LiDAR scan, the
calibration that relates them, and each frame's time. Every input format gives this one shape,
so the pipeline, resume, ranges and scoring never ask where the frames came from."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..calib import Calib
from ..errors import D3LVOInputError
from ..poses import Trajectory, read_poses


@dataclass
class SensorSequence:
    format_name: ClassVar[str] = ""  # `d3lvo run --format`, set by each reader
    root: Path  # the file or folder the user named
    calib: Calib  # P2: the camera's projection, Tr: LiDAR -> the output frame
    frame_names: list[str]
    times: np.ndarray  # seconds, increasing
    frame_label: str  # the frame the poses are written in, said in the run's output
    gt: Trajectory | None = field(default=None, repr=False)
    gt_path: Path | None = None
    calib_path: Path | None = None  # the calibration file read, where there was one (a bag's own: None)

    def __len__(self) -> int:
        return len(self.frame_names)

    def image(self, i: int) -> np.ndarray:
        """(H,W,3) uint8 RGB."""
        raise NotImplementedError

    def scan(self, i: int) -> np.ndarray:
        """(N,4) float32 x, y, z, intensity in the LiDAR frame."""
        raise NotImplementedError

    @property
    def ground_truth(self) -> Trajectory | None:
        """Read when first asked for, as a KITTI sequence's: `d3lvo run` asks before the first
        frame, and a file found beside the recording that does not fit is then a warning, one
        named by --gt an error."""
        if self.gt is None and self.gt_path is not None:
            truth = read_poses(self.gt_path)
            if len(truth) != len(self):
                raise D3LVOInputError(self.gt_path, f"{len(truth)} poses for a sequence of {len(self)} frames")
            self.gt = truth
        return self.gt

    def attach_ground_truth(self, path: str | Path) -> None:
        """Score against this trajectory file (read and checked by `ground_truth`)."""
        self.gt, self.gt_path = None, Path(path)


def check_increasing(path: Path, times: np.ndarray) -> np.ndarray:
    """Stamps that go back would pair the wrong frames and break --realtime pacing."""
    bad = np.nonzero(np.diff(times) <= 0)[0]
    if len(bad):
        k = int(bad[0])
        raise D3LVOInputError(path, f"time of frame {k + 1} ({times[k + 1]:.6f} s) does not come after frame {k}'s "
                                    f"({times[k]:.6f} s)")
    return times


def as_scan(path: Path, xyz: np.ndarray, intensity: np.ndarray | None) -> np.ndarray:
    """Any reader's points -> the (N,4) float32 the pipeline takes; non-finite points dropped
    (organised clouds mark missing returns with NaN)."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    inten = np.zeros(len(xyz), np.float32) if intensity is None else np.asarray(intensity, np.float32).reshape(-1)
    if len(inten) != len(xyz):
        raise D3LVOInputError(path, f"{len(xyz)} points but {len(inten)} intensities")
    scan = np.concatenate([xyz, inten[:, None]], 1)
    keep = np.isfinite(xyz).all(1)
    return np.ascontiguousarray(scan[keep] if not keep.all() else scan)
