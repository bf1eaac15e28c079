"""KITTI calibration files and the camera conventions the toolkit relies on.

Frames: `velo` (LiDAR), `cam0` (rectified left grey camera: KITTI ground truth lives here) and
`cam2` (rectified left colour camera, `image_2`, what the network sees). Rectified cameras share
one orientation, so cam0 -> cam2 is a pure translation b = inv(K2) @ P2[:, 3].
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import D3LVOInputError
from .geometry import is_rigid, make_se3, se3_inv


@dataclass(frozen=True)
class Calib:
    P2: np.ndarray  # (3,4) projection of rectified cam0 coordinates into image_2
    Tr: np.ndarray  # (4,4) velodyne -> rectified cam0
    P0: np.ndarray | None = None
    keys: tuple[str, str] = ("P2", "Tr")  # the file's entries they came from (K and T_cam_lidar: a plain camera's)

    def __post_init__(self):
        """Matrices of the right shape, finite, the extrinsic rigid: a Calib built by hand (the
        streaming API) is checked as a calibration file is, not at the first projection. Held in
        float64, as a file's are: a float32 matrix given by hand projects as the file would."""
        try:
            P2 = np.asarray(self.P2, dtype=np.float64)
            Tr = np.asarray(self.Tr, dtype=np.float64)
        except (TypeError, ValueError):
            raise D3LVOInputError(None, "Calib: P2 and Tr must be numeric matrices") from None
        if P2.shape != (3, 4):
            raise D3LVOInputError(None, f"Calib: P2 must be a 3x4 projection matrix, got shape {P2.shape}")
        if Tr.shape == (3, 4):
            Tr = np.vstack([Tr, [0.0, 0.0, 0.0, 1.0]])
        if Tr.shape != (4, 4):
            raise D3LVOInputError(None, f"Calib: Tr must be a 4x4 (or 3x4) LiDAR-to-camera transform, got shape {Tr.shape}")
        if not (np.isfinite(P2).all() and np.isfinite(Tr).all()):
            raise D3LVOInputError(None, "Calib: P2 and Tr must be finite (a NaN or inf entry)")
        if not is_rigid(Tr):
            raise D3LVOInputError(None, "Calib: Tr must be a rigid transform (an orthonormal rotation, last row 0 0 0 1)")
        object.__setattr__(self, "P2", P2)
        object.__setattr__(self, "Tr", Tr)

    @property
    def K2(self) -> np.ndarray:
        return self.P2[:, :3].copy()

    @property
    def T_cam2_cam0(self) -> np.ndarray:
        """x_cam2 = x_cam0 + b: the image_2 camera centre is -b in cam0 coordinates."""
        b = np.linalg.solve(self.P2[:, :3], self.P2[:, 3])
        return make_se3(np.eye(3), b)

    @property
    def T_cam0_cam2(self) -> np.ndarray:
        return se3_inv(self.T_cam2_cam0)

    @property
    def T_cam2_velo(self) -> np.ndarray:
        return self.T_cam2_cam0 @ self.Tr

    @property
    def P_velo_to_image2(self) -> np.ndarray:
        """(3,4) matrix taking homogeneous LiDAR points straight to image_2 pixels."""
        return self.P2 @ self.Tr

    def to_text(self) -> str:
        """KITTI odometry calib.txt (P0..P3 written as P2 where the others are unknown)."""
        P0 = self.P0 if self.P0 is not None else np.hstack([self.K2, np.zeros((3, 1))])
        rows = [("P0", P0), ("P1", P0), ("P2", self.P2), ("P3", self.P2), ("Tr", self.Tr[:3])]
        return "".join(f"{k}: " + " ".join(f"{v:.12e}" for v in np.asarray(m).reshape(-1)) + "\n" for k, m in rows)


def _as_4x4(path: Path, key: str, vals: list[float]) -> np.ndarray:
    if len(vals) == 12:
        return np.vstack([np.asarray(vals).reshape(3, 4), [0, 0, 0, 1]])
    if len(vals) == 16:
        T = np.asarray(vals).reshape(4, 4)
        if not np.allclose(T[3], [0, 0, 0, 1]):
            raise D3LVOInputError(path, f"{key}: last row of the 4x4 matrix must be 0 0 0 1")
        return T
    raise D3LVOInputError(path, f"{key} has {len(vals)} numbers, expected 12 (3x4) or 16 (4x4)")


def parse_calib(path: str | Path) -> Calib:
    """Read odometry (`P0..P3`, `Tr`) or object-benchmark (`R0_rect`, `Tr_velo_to_cam`) calib files,
    or a plain camera's: `K` (9 numbers) and `T_cam_lidar` (12 or 16), poses then in that camera."""
    path = Path(path)
    if not path.is_file():
        raise D3LVOInputError(path, "is a folder; a calibration file was expected" if path.is_dir()
                              else "calibration file not found")
    entries: dict[str, list[float]] = {}
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        if ":" not in line:
            raise D3LVOInputError(path, f"line {lineno} has no 'KEY:' prefix: {line[:60]!r}")
        key, rest = line.split(":", 1)
        try:
            entries[key.strip()] = [float(v) for v in rest.split()]
        except ValueError:
            raise D3LVOInputError(path, f"line {lineno} ({key.strip()}) is not numeric") from None

    cam_key = "P2" if "P2" in entries else "K" if "K" in entries else None
    if cam_key is None:
        raise D3LVOInputError(path, "no P2 (image_2 projection) or K (camera matrix) entry")
    if cam_key == "K":
        if len(entries["K"]) != 9:
            raise D3LVOInputError(path, f"K has {len(entries['K'])} numbers, expected 9 (3x3)")
        entries["P2"] = list(np.hstack([np.asarray(entries["K"]).reshape(3, 3), np.zeros((3, 1))]).reshape(-1))
    if len(entries["P2"]) != 12:
        raise D3LVOInputError(path, f"P2 has {len(entries['P2'])} numbers, expected 12")
    P2 = np.asarray(entries["P2"]).reshape(3, 4)
    if not (P2[0, 0] > 0 and P2[1, 1] > 0):
        raise D3LVOInputError(path, f"{cam_key}'s focal lengths must be positive (fx {P2[0, 0]:g}, fy {P2[1, 1]:g})")
    if abs(np.linalg.det(P2[:, :3])) < 1e-9:
        raise D3LVOInputError(path, f"{cam_key}'s left 3x3 block is singular")

    tr_key = next((k for k in ("Tr", "Tr_velo_to_cam", "Tr_velo_cam", "T_cam_lidar") if k in entries), None)
    if tr_key is None:
        raise D3LVOInputError(path, "no LiDAR extrinsic (Tr, Tr_velo_to_cam, Tr_velo_cam or T_cam_lidar)")
    Tr = _as_4x4(path, tr_key, entries[tr_key])
    rect_key = next((k for k in ("R0_rect", "R_rect", "R0") if k in entries), None)
    if rect_key is not None and tr_key not in ("Tr", "T_cam_lidar"):
        R0 = np.asarray(entries[rect_key])
        if R0.size != 9:
            raise D3LVOInputError(path, f"{rect_key} has {R0.size} numbers, expected 9")
        Tr = make_se3(R0.reshape(3, 3), np.zeros(3)) @ Tr
    R = Tr[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
        raise D3LVOInputError(path, f"{tr_key}'s rotation block is not orthonormal")
    P0 = np.asarray(entries["P0"]).reshape(3, 4) if len(entries.get("P0", [])) == 12 else None
    return Calib(P2=P2, Tr=Tr, P0=P0, keys=(cam_key, tr_key))


# below this share of a scan's returns in the image, a warning: a forward camera with a 360-degree
# LiDAR (KITTI's rig, the synthetic drives) sees a good part of every scan (tests/test_calib.py)
FEW_IN_VIEW = 0.02
# a scan whose median return is farther than this is not in metres: a 64-beam scan of a street
# has its median within tens of metres, and long-range LiDARs within ~100
MAX_MEDIAN_RANGE = 500.0
# no LiDAR return has a coordinate this far (m), nor one in millimetres; a float64 file read as
# float32 x, y, z, r puts a quarter or more of its rows there (the halves of doubles read as floats)
FAR_OUT = 1e6
FAR_OUT_SHARE = 0.01


def check_fit(calib: Calib, width: int, height: int, scan: np.ndarray, where: str | Path, frame: str,
              scan_where: str | Path | None = None) -> None:
    """The calibration against one frame's image size and scan, before a run: a principal point
    outside the image (images of another size), or a scan of which no return lands in the image
    (the LiDAR extrinsic of another rig), is an error; a principal point far from the centre or
    few returns in view a warning. Either would otherwise run to a wrong trajectory without a word.
    A scan that is not float32 metres is an error naming `scan_where` (the scan's file, where known)."""
    from .projection import PROJECTION_MIN_DEPTH, project_points

    cx, cy = calib.P2[0, 2] / calib.P2[2, 2], calib.P2[1, 2] / calib.P2[2, 2]
    size = f"{width}x{height}"
    if not (0 <= cx < width and 0 <= cy < height):
        raise D3LVOInputError(where, f"the calibration's principal point ({cx:.1f}, {cy:.1f}) lies outside frame "
                                     f"{frame}'s {size} image: the calibration is for images of another size")
    if not (0.1 <= cx / width <= 0.9 and 0.1 <= cy / height <= 0.9):
        warnings.warn(f"{where}: the calibration's principal point ({cx:.1f}, {cy:.1f}) is far from the centre of "
                      f"frame {frame}'s {size} image: is the calibration for images of another size?", stacklevel=2)
    pts = np.asarray(scan)[:, :3]
    pts = pts[np.isfinite(pts).all(1)]
    if len(pts) < 1000:  # an empty or sparse scan: its own warning, and too few to judge by
        return
    far = float((np.abs(pts) > FAR_OUT).any(axis=1).mean())
    if far > FAR_OUT_SHARE:
        raise D3LVOInputError(scan_where, f"{far:.0%} of frame {frame}'s {len(pts)} LiDAR returns have a "
                                          f"coordinate beyond {FAR_OUT / 1000:,.0f} km: a scan must be float32 x, y, z, "
                                          "reflectance in metres (a float64 file reads like this)")
    reach = float(np.median(np.linalg.norm(pts.astype(np.float64), axis=1)))  # float64: no overflow on garbage
    if reach > MAX_MEDIAN_RANGE:
        raise D3LVOInputError(scan_where, f"the median range of frame {frame}'s {len(pts)} LiDAR returns is "
                                          f"{reach:.0f} m: points must be in metres (millimetres or centimetres?)")
    seen = len(project_points(pts, calib.P_velo_to_image2, width, height, PROJECTION_MIN_DEPTH)[2])
    if seen == 0:
        raise D3LVOInputError(where, f"none of the {len(pts)} LiDAR returns of frame {frame} lands in its {size} "
                                     "image: the calibration's LiDAR-to-camera transform does not fit this recording")
    if seen < FEW_IN_VIEW * len(pts):
        warnings.warn(f"{where}: only {seen} of the {len(pts)} LiDAR returns of frame {frame} ({seen / len(pts):.1%}) "
                      f"land in its {size} image: does the calibration fit this recording?", stacklevel=2)
