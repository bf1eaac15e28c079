"""The classical tracker on one frame pair of a drive, started from the true motion and from rest.

    .venv/bin/python scripts/track_pair.py DRIVE I [--affine-brightness] [--static-only]

Tracks frame I+1 against frame I's LiDAR points with the bundled model's classical mode (`--method
direct`, `DirectConfig.of_model`), from the drive's true motion (`poses.txt`), from 98 % of it and
from rest, and prints where each start ends and the pair's photometric cost there
(`direct.motion_cost`: median residual after a gain and offset fit, lower is better). A solve
that leaves the true motion for a pose of higher cost is the solver's objective failing, not its
start; `--affine-brightness` refits frame t's grey as a ref + b at every step. Then, from the true
motion without the finest level's restart (`fine_restart`), coarse to fine on all levels, on the
two finest and on the finest alone, each with its MSAC gain over the solve on all levels
(`direct.consensus_gain`, by which the restart is kept above `fine_restart`) and its LiDAR depth
error (frame I's points against frame I+1's own scan, which sees the forward step that weak
texture may not): a pyramid level that holds a wrong minimum shows there.
`--static-only` keeps only the points on pixels that frame I's motion mask (`motion_2/`, drives
rendered with `--traffic`) marks static: whether what moves is to blame.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.direct import (DirectConfig, DirectOdometry, TrackedFrame, consensus_gain, lidar_depth_error,
                                 motion_cost, track)
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.geometry import change_frame, relative
from d3lvo_deploy.manifest import load_manifest
from d3lvo_deploy.poses import read_poses
from d3lvo_deploy.sequence import KittiSequence
from masked_tracker import untrusted, without  # scripts/ is on the path of a script run from it


def main(drive: str, i: int, affine: bool, static_only: bool) -> None:
    seq = KittiSequence.open(drive)
    if not 0 <= i < len(seq) - 1:
        sys.exit(f"{drive}: frame {i} has no next frame ({len(seq)} frames)")
    cfg = replace(DirectConfig.of_model(load_manifest(bundled_model_dir())["model_config"]), affine_brightness=affine)
    odo = DirectOdometry(seq.calib, cfg)
    a, b = odo._frame(seq.image(i), seq.scan(i)), odo._frame(seq.image(i + 1), seq.scan(i + 1))
    if static_only:
        a = without(a, untrusted(Path(drive), i, shadows=False))
    G = read_poses(f"{drive}/poses.txt").poses
    truth = change_frame(relative(G[i], G[i + 1]), seq.calib.T_cam2_cam0)  # image_2 motion, frame i+1 in frame i
    short = truth.copy()
    short[:3, 3] *= 0.98
    print(f"pair {i}-{i + 1}: {len(a.points)} points, true step {np.linalg.norm(truth[:3, 3]):.3f} m, "
          f"cost there {motion_cost(a, b, truth):.4f}, at rest {motion_cost(a, b, np.eye(4)):.4f}")
    for name, start in (("the true motion", truth), ("98 % of it", short), ("rest", np.eye(4))):
        A = track(a, b, start, cfg)
        print(f"from {name:16s} -> step {np.linalg.norm(A[:3, 3]):.3f} m, {np.linalg.norm((np.linalg.inv(truth) @ A)[:3, 3]):.3f} m "
              f"off, cost {motion_cost(a, b, A):.4f}")
    # frame i+1's own LiDAR depth, as the tracker keeps it (pt_restart_depth, pt_scan_gate)
    depth, K = b.depth, seq.calib.K2
    if depth is None:
        sys.exit("the bundled model's classical mode keeps no scan depth (its pt_restart_depth and pt_scan_gate are 0)")
    print(f"LiDAR depth error (median |d - z| / z against frame {i + 1}'s scan) at the true motion "
          f"{lidar_depth_error(a.points, truth, depth, K):.4f}")
    # where the pyramid loses it: from the true motion without the restart, on the finest levels
    # only, and the MSAC gain over the solve on all levels by which the restart is kept or not
    full = None
    for n in range(cfg.levels, 0, -1):
        c = replace(cfg, levels=n, iterations=cfg.iterations[-n:], fine_restart=0.0)
        A = track(TrackedFrame(a.levels[:n], a.points), TrackedFrame(b.levels[:n], b.points), truth, c)
        full = A if full is None else full
        print(f"from the true motion, the {n} finest level(s), no restart -> step {np.linalg.norm(A[:3, 3]):.3f} m, "
              f"{np.linalg.norm((np.linalg.inv(truth) @ A)[:3, 3]):.3f} m off, cost {motion_cost(a, b, A):.4f}, "
              f"gain over all levels {consensus_gain(a, b, A, full):+.4f}, LiDAR depth error "
              f"{lidar_depth_error(a.points, A, depth, K):.4f}")


if __name__ == "__main__":
    unknown = [a for a in sys.argv[1:] if a.startswith("--") and a not in ("--affine-brightness", "--static-only")]
    if unknown:
        sys.exit(f"error: unknown option {unknown[0]} (--affine-brightness, --static-only)")
    args = [a for a in sys.argv[1:] if a not in ("--affine-brightness", "--static-only")]
    if len(args) != 2 or not args[1].isdigit():
        sys.exit(__doc__)
    try:
        main(args[0], int(args[1]), "--affine-brightness" in sys.argv, "--static-only" in sys.argv)
    except D3LVOInputError as e:  # a missing drive or poses.txt: one line
        sys.exit(f"error: {e}")
