"""A Rerun recording (`.rrd`) of a run, for the Rerun viewer (`rerun FILE.rrd`): the growing
trajectory and the LiDAR scans in the first frame's coordinates every frame, and on chosen frames
the camera with what the network saw (image, LiDAR and completed depth, flow, pose confidence).

Rerun (`rerun-sdk`, the `[rerun]` extra) rather than a home-made viewer: it gives 3-D scenes,
time scrubbing and image/point overlays of a robotics log out of the box. It is imported only
when `--rerun` is given, so the vehicle install does not need it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .calib import Calib
from .errors import D3LVOInputError

MAX_POINTS = 20000  # per scan: enough to see the street, keeps a 200-frame recording small


class RerunRecorder:
    def __init__(self, path: Path, calib: Calib, app_id: str = "d3lvo"):
        import rerun as rr

        self.rr = rr
        self.rec = rr.RecordingStream(app_id)
        try:
            self.rec.save(str(path))
        except Exception as e:  # rerun raises its own error types for an unwritable file
            raise D3LVOInputError(path, f"cannot write the Rerun recording ({e})") from None
        self.T_cam0_velo = calib.T_cam0_cam2 @ calib.T_cam2_velo
        self.T_cam0_cam2 = calib.T_cam0_cam2
        self.positions: list[np.ndarray] = []
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)  # KITTI cameras: x right, y down, z forward

    def frame(self, i: int, pose: np.ndarray, points: np.ndarray | None, view: dict | None = None,
              K: np.ndarray | None = None) -> None:
        """`pose`: 4x4 cam0 pose; `points`: the (N,4) scan; `view`: `viz.network_view` of a
        chosen frame, with `K` the network view's camera matrix."""
        rr = self.rr
        self.rec.set_time("frame", sequence=i)
        self.positions.append(pose[:3, 3].copy())
        self.rec.log("world/trajectory", rr.LineStrips3D([np.array(self.positions)], colors=[[230, 60, 40]]))
        if points is not None and len(points):
            step = max(1, -(-len(points) // MAX_POINTS))  # at most MAX_POINTS
            p = points[::step, :3].astype(np.float64)
            T = pose @ self.T_cam0_velo
            world = p @ T[:3, :3].T + T[:3, 3]
            self.rec.log("world/lidar", rr.Points3D(world.astype(np.float32), radii=0.03,
                                                    colors=_height_colours(p[:, 2])))
        if view is None or K is None:
            return
        from .viz import colourise, flow_to_rgb

        cam = pose @ self.T_cam0_cam2
        h, w = view["image"].shape[:2]
        self.rec.log("world/camera", rr.Transform3D(translation=cam[:3, 3], mat3x3=cam[:3, :3]))
        self.rec.log("world/camera", rr.Pinhole(image_from_camera=K, width=w, height=h))
        self.rec.log("world/camera/image", rr.Image(view["image"]).compress(jpeg_quality=85))
        self.rec.log("world/camera/lidar_depth", rr.DepthImage(view["lidar_m"], meter=1.0))
        if view["dense_m"] is not None:
            self.rec.log("completed_depth", rr.DepthImage(view["dense_m"], meter=1.0))
        if view["flow"] is not None:
            self.rec.log("flow", rr.Image(flow_to_rgb(view["flow"])))
        if view["confidence"] is not None:
            hi = 1.0 if view.get("points_head") else 2.0  # 1 - p(moves) for the point head
            self.rec.log("confidence", rr.Image(colourise(view["confidence"], 0.0, hi)))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


def _height_colours(z: np.ndarray) -> np.ndarray:
    """Scan height (Velodyne z, metres) -> RGB, so the ground and the buildings read apart."""
    from .viz import colourise

    return colourise(z[None, :], -2.0, 3.0)[0]
