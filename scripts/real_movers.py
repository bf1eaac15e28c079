"""Which vehicles of the 20 real KITTI frames move, by LiDAR alone, and does the confidence see them?

The real frames have no motion masks, so the labels come from the scans and an independent
LiDAR-only odometry (KISS-ICP, the `[test]` extra):

- the ego motion between frames a and b is KISS-ICP's, refined by a robust translation-only ICP of
  the whole scan (points above the road, 3-30 m);
- a vehicle (the LiDAR points in an image box of frame a) is moved to frame b as if it stood
  still, then a translation-only ICP of that cluster against scan b gives its own displacement;
- per point of the bundled model's solver list (frame t-1 of each pair): static where, moved to
  frame t-1 +- 6 as if it stood still, a return of that scan lies within 0.1 m (or it is on the
  road), moving where none lies within 0.4 m (within 30 m), else left out; then the area under the
  ROC curve of 1 - the point's weight for moving against static points (uniform weights: 0.5).

    .venv/bin/python scripts/real_movers.py [SEQ_DIR]     # ~1 min on 2 cores; the boxes are r0926 frame 0's
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from d3lvo_deploy.backends import SessionConfig
from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.lidar_reference import kiss_icp_poses
from d3lvo_deploy.metrics import auroc
from d3lvo_deploy.odometry import Odometry
from d3lvo_deploy.points import project
from d3lvo_deploy.sequence import KittiSequence

ROAD_Z = -1.4  # velodyne z (m) above which a return is not the road (the sensor is 1.73 m up)
STEP = 6  # frames between a and b: 0.6 s
# image_2 boxes (x0, y0, x1, y1) of frame 0's vehicles, and a static control
BOXES = {"silver car on the left (being passed)": (67, 180, 413, 370), "car ahead": (540, 180, 700, 320),
         "red utility truck ahead left": (340, 150, 500, 260), "cement truck's cab (right)": (790, 40, 1000, 300),
         "trees and poles (static control)": (0, 100, 330, 165)}


class Nearest:
    """Nearest return of a scan (FLANN k-d trees from OpenCV, already a runtime dependency)."""

    def __init__(self, pts: np.ndarray):
        self.pts = np.ascontiguousarray(pts, np.float32)
        self.index = cv2.flann_Index(self.pts, {"algorithm": 1, "trees": 4})

    def query(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx, d2 = self.index.knnSearch(np.ascontiguousarray(q, np.float32), 1, params={"checks": 64})
        return np.sqrt(d2[:, 0]), idx[:, 0]


def own_translation(q: np.ndarray, target: Nearest, iterations: int = 25) -> tuple[np.ndarray, float]:
    """Robust translation-only ICP of points q onto a scan: (translation, median distance after)."""
    t = np.zeros(3)
    for _ in range(iterations):
        d, idx = target.query(q + t)
        keep = d < max(0.3, 2 * np.median(d))
        t = t + np.median(target.pts[idx[keep]] - (q + t)[keep], axis=0)
    return t, float(np.median(target.query(q + t)[0]))


def above_road(scan: np.ndarray) -> np.ndarray:
    return scan[scan[:, 2] > ROAD_Z, :3]


def ego_motion(seq: KittiSequence, poses: list, a: int, b: int) -> np.ndarray:
    """(4,4) velodyne a -> velodyne b: KISS-ICP's, its translation refined on the whole scan."""
    M = np.linalg.inv(poses[b]) @ poses[a]
    s = above_road(seq.scan(a))
    r = np.linalg.norm(s[:, :2], axis=1)
    s = s[(r > 3) & (r < 30)][::4]
    t, _ = own_translation(s @ M[:3, :3].T + M[:3, 3], Nearest(above_road(seq.scan(b))), 20)
    M[:3, 3] += t
    return M


def in_box(seq: KittiSequence, scan: np.ndarray, box: tuple, max_depth: float) -> np.ndarray:
    T = seq.calib.T_cam2_velo
    X = scan[:, :3] @ T[:3, :3].T + T[:3, 3]
    uv, _ = project(np.c_[X[:, :2], np.maximum(X[:, 2], 0.5)], seq.calib.K2)  # behind: masked below
    u, v = uv.T
    x0, y0, x1, y1 = box
    keep = (X[:, 2] > 0.5) & (u >= x0) & (u <= x1) & (v >= y0) & (v <= y1) & (X[:, 2] < max_depth)
    return scan[keep & (scan[:, 2] > ROAD_Z), :3]


def main(seq_dir: str) -> None:
    seq = KittiSequence.open(Path(seq_dir))
    poses = kiss_icp_poses(seq)
    M = ego_motion(seq, poses, 0, STEP)
    target = Nearest(above_road(seq.scan(STEP)))
    print(f"vehicles of frame 0, own displacement over frames 0-{STEP} ({STEP / 10:.1f} s; the car moves "
          f"{np.linalg.norm(M[:3, 3]):.2f} m):")
    for name, box in BOXES.items():
        pts = in_box(seq, seq.scan(0), box, 80.0 if "static" in name else 25.0)
        t, after = own_translation(pts @ M[:3, :3].T + M[:3, 3], target)
        print(f"  {name:38s} {len(pts):5d} returns, moved {np.linalg.norm(t):.2f} m "
              f"(x forward {t[0]:+.2f}, y left {t[1]:+.2f}), median misfit after {after:.3f} m")

    odo = Odometry(bundled_model_dir(), seq.calib, SessionConfig(threads=2))
    odo.keep_outputs = True
    velo_from_cam = np.linalg.inv(seq.calib.T_cam2_velo)
    scores, labels = [], []
    prev = None  # frame t-1's solver points: the list the pair's weights belong to
    for i in range(len(seq)):
        frame = odo.prepare(seq.image(i), seq.scan(i))
        odo.step_prepared(frame)
        if prev is None:
            prev = frame.solver.points
            continue
        w = odo.last["flowpose"]["point_weights"][0, : len(prev)]
        a = i - 1
        b = a + STEP if a + STEP < len(seq) else a - STEP
        X = prev @ velo_from_cam[:3, :3].T + velo_from_cam[:3, 3]
        Mab = ego_motion(seq, poses, a, b)
        d, _ = Nearest(seq.scan(b)[:, :3]).query(X @ Mab[:3, :3].T + Mab[:3, 3])
        near, road = np.linalg.norm(X[:, :2], axis=1) < 30, X[:, 2] < ROAD_Z - 0.05
        y = np.full(len(prev), -1)
        y[((d < 0.1) | road) & near] = 0
        y[(d > 0.4) & ~road & near] = 1
        scores.append(1.0 - w[y >= 0])
        labels.append(y[y >= 0])
        prev = frame.solver.points
    s, y = np.concatenate(scores), np.concatenate(labels)
    print(f"solver points of {len(seq) - 1} pairs: {int(y.sum())} moving, {int((1 - y).sum())} static by LiDAR; "
          f"mean weight {1 - s[y == 1].mean():.2f} moving, {1 - s[y == 0].mean():.2f} static; "
          f"AUROC of low weight for moving points {auroc(s, y):.3f} (uniform weights 0.500)")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1].startswith("-"):
        sys.exit(__doc__)
    # the boxes are drawn on r0926's frame 0: the default is those frames, found from the checkout
    default = Path(__file__).resolve().parents[2] / "shared/data/kitti_raw_snippet/sequences/r0926"
    try:
        main(sys.argv[1] if len(sys.argv) > 1 else str(default))
    except D3LVOInputError as e:
        sys.exit(f"error: {e}")
