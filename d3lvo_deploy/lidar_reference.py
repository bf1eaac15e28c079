"""LiDAR-only odometry as the independent reference for real frames without ground truth.

KISS-ICP (the `[test]` extra, not a runtime dependency: imported only when called) with its
defaults for a 100 m sensor and no deskewing, since KITTI's scans carry no per-point times. The
tests hold the visual methods to it, and `scripts/real_movers.py` reads which vehicles move by it.
"""

from __future__ import annotations

import numpy as np

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
