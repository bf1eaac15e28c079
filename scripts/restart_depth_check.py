"""The classical mode with a second way to keep the finest level's restart: frame t's own LiDAR scan.

    .venv/bin/python scripts/restart_depth_check.py DRIVE OUT.txt [--ratio 0.5]

Runs the bundled model's classical mode (`d3lvo run --method direct`) over DRIVE and writes its
cam0 poses (KITTI format) to OUT.txt, with one change: the finest level's restart is kept where
its MSAC gain exceeds `fine_restart` (as shipped) or where its LiDAR depth error against frame t's
own scan is below `--ratio` times the coarse-to-fine pose's (`track_pair.lidar_depth_error`: the
median |d - z| / z of frame t-1's points moved by the pose, at the pixels where frame t has a
return). Where few points constrain the forward step, the photometric costs can prefer a pose
that is half a metre short; the scan sees the step (docs/evaluation.md, seed 317). Score OUT.txt
with `d3lvo eval --gt DRIVE/poses.txt --est OUT.txt`.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from track_pair import lidar_depth, lidar_depth_error  # noqa: E402

from d3lvo_deploy import direct  # noqa: E402
from d3lvo_deploy.bundled import bundled_model_dir  # noqa: E402
from d3lvo_deploy.manifest import load_manifest  # noqa: E402
from d3lvo_deploy.poses import write_poses  # noqa: E402
from d3lvo_deploy.sequence import KittiSequence  # noqa: E402


def main(drive: str, out: str, ratio: float) -> None:
    seq = KittiSequence.open(drive)
    cfg = direct.DirectConfig.of_model(load_manifest(bundled_model_dir())["model_config"])
    shipped, K = direct.track, seq.calib.K2
    frame_t = {}  # frame t's LiDAR depth at the camera's resolution, set per frame below

    def track(prev, cur, start, c):
        coarse_to_fine = shipped(prev, cur, start, replace(c, fine_restart=0.0))
        if c.fine_restart <= 0 or c.levels < 2:
            return coarse_to_fine
        # the shipped restart: the finest level alone from the start
        finest = replace(c, levels=1, iterations=c.iterations[-1:], fine_restart=0.0)
        restart = shipped(direct.TrackedFrame(prev.levels[:1], prev.points), direct.TrackedFrame(cur.levels[:1], []),
                          start, finest)
        depth = frame_t["depth"]
        if (direct.consensus_gain(prev, cur, restart, coarse_to_fine) > c.fine_restart  # the shipped rule
                or lidar_depth_error(prev.points, restart, depth, K)
                < ratio * lidar_depth_error(prev.points, coarse_to_fine, depth, K)):
            return restart
        return coarse_to_fine

    direct.track = track
    odo = direct.DirectOdometry(seq.calib, cfg)
    poses = []
    for i in range(len(seq)):
        image, scan = seq.image(i), seq.scan(i)
        frame_t["depth"] = lidar_depth(image, scan, seq.calib)
        poses.append(odo.step(image, scan))
    write_poses(out, np.array(poses))


if __name__ == "__main__":
    args = sys.argv[1:]
    ratio = 0.5
    if "--ratio" in args:
        k = args.index("--ratio")
        ratio = float(args[k + 1])
        del args[k:k + 2]
    if len(args) != 2:
        sys.exit(__doc__)
    main(args[0], args[1], ratio)
