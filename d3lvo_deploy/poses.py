"""Trajectory files: KITTI (12 numbers), indexed KITTI (frame index + 12) and TUM (t x y z qx qy qz qw)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import D3LVOInputError
from .geometry import make_se3, quat_to_rot, rot_to_quat


@dataclass
class Trajectory:
    """Absolute poses (N,4,4) with the frame index of each (skipped frames allowed) and optional stamps."""

    poses: np.ndarray
    frame_ids: np.ndarray
    timestamps: np.ndarray | None = None
    numbered: bool = False  # the file numbered its frames (kitti-odom-eval's 13 columns)

    def __len__(self) -> int:
        return len(self.poses)

    @classmethod
    def from_poses(cls, poses: np.ndarray, timestamps: np.ndarray | None = None) -> "Trajectory":
        """(N,4,4) poses, or (N,3,4) as KITTI writes them; anything else is one error, not rows
        of other poses reshaped into these."""
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim == 3 and poses.shape[1:] == (3, 4):
            poses = np.concatenate([poses, np.broadcast_to([[[0.0, 0.0, 0.0, 1.0]]], (len(poses), 1, 4))], 1)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise D3LVOInputError(None, f"poses must be (N,4,4) or (N,3,4), got shape {poses.shape}")
        if timestamps is not None and len(timestamps) != len(poses):
            raise D3LVOInputError(None, f"{len(timestamps)} timestamps for {len(poses)} poses")
        return cls(poses, np.arange(len(poses)), timestamps)


def _text(path: Path) -> str:
    """The file's text; a byte-order mark says UTF-16 (Windows PowerShell's `>`) or UTF-8 with a
    BOM (Notepad), which would otherwise read as a first line that is not numbers."""
    raw = path.read_bytes()
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):
        return raw.decode("utf-16", errors="replace")
    return raw.decode("utf-8-sig", errors="replace")


def _parse_rows(path: Path) -> tuple[list[list[float]], list[int]]:
    """The rows of numbers and their line numbers (blank lines and # comments left out)."""
    rows: list[list[float]] = []
    lines: list[int] = []
    for lineno, line in enumerate(_text(path).splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            rows.append([float(v) for v in s.replace(",", " ").split()])
        except ValueError:
            raise D3LVOInputError(path, f"line {lineno} is not a row of numbers: {s[:60]!r}") from None
        lines.append(lineno)
    return rows, lines


# a KITTI line's rotation may be written with few digits (two decimals put R R^T up to ~0.015 from
# I), not with a wrong matrix; the published trajectories and ground truth in ../shared/data are
# within 1e-6
ROTATION_TOLERANCE = 0.05


def read_poses(path: str | Path, fmt: str = "auto") -> Trajectory:
    """Read a trajectory; `fmt` is auto|kitti|kitti_indexed|tum. Auto decides by the column count."""
    path = Path(path)
    if not path.is_file():
        raise D3LVOInputError(path, "is a folder; a pose file was expected" if path.is_dir() else "pose file not found")
    rows, lines = _parse_rows(path)
    if not rows:
        raise D3LVOInputError(path, "pose file is empty")
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        counts = [len(r) for r in rows]
        usual = max(widths, key=lambda w: (counts.count(w), w == counts[0]))  # ties: the first line's
        k = next(i for i, c in enumerate(counts) if c != usual)
        raise D3LVOInputError(path, f"line {lines[k]} has {counts[k]} numbers where the others have {usual} "
                                    f"(column counts {sorted(widths)})")
    ncol = widths.pop()
    if fmt == "auto":
        fmt = {12: "kitti", 13: "kitti_indexed", 8: "tum"}.get(ncol, "")
        if not fmt:
            raise D3LVOInputError(
                path, f"{ncol} columns per line: expected 12 (KITTI), 13 (index + KITTI) or 8 (TUM)"
            )
    expected = {"kitti": 12, "kitti_indexed": 13, "tum": 8}
    if fmt not in expected:
        raise ValueError(f"unknown pose format {fmt!r}")
    if ncol != expected[fmt]:
        raise D3LVOInputError(path, f"{ncol} columns per line, but {fmt} needs {expected[fmt]}")
    a = np.asarray(rows, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        bad = int(np.argmax(~np.all(np.isfinite(a), axis=1)))
        raise D3LVOInputError(path, f"pose {bad} contains NaN or infinity")
    stamps = None
    if fmt == "tum":
        stamps = a[:, 0]
        norms = np.linalg.norm(a[:, 4:8], axis=1)
        if np.any(norms < 1e-12):
            raise D3LVOInputError(path, f"pose {int(np.argmax(norms < 1e-12))}: its quaternion qx qy qz qw is all zero")
        if np.any(np.diff(stamps) <= 0):
            raise D3LVOInputError(path, f"pose {int(np.argmax(np.diff(stamps) <= 0)) + 1}: its time does not come after "
                                        "the previous pose's (TUM times must increase)")
        poses = make_se3(quat_to_rot(a[:, 4:8], scalar_first=False), a[:, 1:4])
        ids = np.arange(len(a))
    else:
        if fmt == "kitti_indexed":
            ids = a[:, 0].astype(np.int64)
            if np.any(ids != a[:, 0]) or np.any(np.diff(ids) <= 0):
                raise D3LVOInputError(path, "frame indices in column 1 must be increasing integers")
            a = a[:, 1:]
        else:
            ids = np.arange(len(a))
        poses = np.tile(np.eye(4), (len(a), 1, 1))
        poses[:, :3, :] = a.reshape(-1, 3, 4)
        R = poses[:, :3, :3]
        off = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(R)
        bad = (off > ROTATION_TOLERANCE) | (det <= 0)  # a reflection, or a block of zeros, is no rotation either
        if np.any(bad):
            k = int(np.argmax(bad))
            why = f"its determinant is {det[k]:.3g}" if det[k] <= 0 else \
                f"R R^T differs from I by {off[k]:.3g}, more than {ROTATION_TOLERANCE}"
            raise D3LVOInputError(path, f"pose {k}: its 3x3 block is not a rotation ({why}); a KITTI line is the 3x4 "
                                        "matrix [R | t], row by row")
    return Trajectory(poses, ids, stamps, numbered=fmt == "kitti_indexed")


def format_kitti_line(T: np.ndarray, spec: str = ".9e") -> str:
    return " ".join(f"{v:{spec}}" for v in np.asarray(T)[:3, :4].reshape(-1))


def format_tum_line(T: np.ndarray, stamp: float, spec: str = ".9f") -> str:
    q = rot_to_quat(np.asarray(T)[:3, :3], scalar_first=False)
    t = np.asarray(T)[:3, 3]
    return f"{stamp:.6f} " + " ".join(f"{v:{spec}}" for v in (*t, *q))


def write_poses(path: str | Path, poses: np.ndarray, fmt: str = "kitti", timestamps: np.ndarray | None = None) -> None:
    """Write (N,4,4) poses as KITTI or TUM (TUM stamps default to 10 Hz)."""
    path = Path(path)
    poses = np.asarray(poses).reshape(-1, 4, 4)
    if fmt == "kitti":
        lines = [format_kitti_line(T) for T in poses]
    elif fmt == "tum":
        stamps = np.arange(len(poses)) * 0.1 if timestamps is None else np.asarray(timestamps)
        lines = [format_tum_line(T, s) for T, s in zip(poses, stamps)]
    else:
        raise ValueError(f"unknown pose format {fmt!r}")
    path.write_text("\n".join(lines) + ("\n" if lines else ""))
