"""LiDAR-only odometry as the independent reference for real frames without ground truth.

KISS-ICP (the `[test]` extra, not a runtime dependency: imported only when called) with its
defaults for a 100 m sensor and no deskewing, since KITTI's scans carry no per-point times. The
tests hold the visual methods to it, and `scripts/real_movers.py` reads which vehicles move by it.
"""

from __future__ import annotations

import numpy as np

from .geometry import se3_inv
from .sequence import KittiSequence


def kiss_icp_poses(seq: KittiSequence) -> np.ndarray:
    """(N,4,4) poses of the velodyne frame, first scan identity."""
    from kiss_icp.config import KISSConfig
    from kiss_icp.kiss_icp import KissICP

    cfg = KISSConfig()
    cfg.data.deskew = False
    cfg.mapping.voxel_size = cfg.data.max_range / 100.0
    odo, poses = KissICP(cfg), []
    for i in range(len(seq)):
        pts = seq.scan(i)[:, :3].astype(np.float64)
        odo.register_frame(pts, np.zeros(len(pts)))
        poses.append(odo.last_pose.copy())
    return np.array(poses)


def kiss_icp_cam0(seq: KittiSequence) -> np.ndarray:
    """`kiss_icp_poses` moved into cam0 (KITTI's pose frame), first pose identity: comparable with
    a `d3lvo run` trajectory of the same frames."""
    Tr = seq.calib.Tr
    return np.array([Tr @ p @ se3_inv(Tr) for p in kiss_icp_poses(seq)])


def have_kiss_icp() -> bool:
    """Whether the reference can be computed here (the `[test]` extra): imported, not only found,
    since its compiled part may fail to load."""
    try:
        import kiss_icp.kiss_icp  # noqa: F401
    except (ImportError, OSError):
        return False
    return True
