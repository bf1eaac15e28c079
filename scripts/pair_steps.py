"""Per pair, the step the bundled model kept, its weighted and classical solves, and where it started,
against the drive's ground truth: where a stretch of pairs loses the motion, and how it starts.

    .venv/bin/python scripts/pair_steps.py DRIVE FIRST LAST

Runs the bundled model (onnxruntime, two threads, as `d3lvo run DRIVE`) from frame 0 to LAST and
prints pairs FIRST..LAST: the true step's length (image_2, m), then for the kept pose, the
weighted pose (where the next pair starts) and the classical pose their step's length and their
error against the true motion (m), the start's error, and the share of frame t-1's points the
network distrusts (weight under 0.5). docs/evaluation.md ("The motion guard") quotes seed 323.
"""

from __future__ import annotations

import sys

import numpy as np

from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.datasets import open_sequence
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.geometry import change_frame, relative
from d3lvo_deploy.odometry import Odometry
from d3lvo_deploy.onnx_model import SessionConfig


def main(drive: str, first: int, last: int) -> None:
    seq = open_sequence(drive)
    gt = seq.ground_truth
    if gt is None:
        raise D3LVOInputError(seq.root, "has no ground truth (poses.txt)")
    if not 1 <= first <= last < len(seq):
        raise D3LVOInputError(seq.root, f"pairs {first}..{last} are outside 1..{len(seq) - 1}")
    odo = Odometry(bundled_model_dir(), seq.calib, SessionConfig(backend="onnxruntime", threads=2))
    odo.keep_outputs = True
    seen: dict = {}
    flow_pose = odo.model.flow_pose

    def recorded(prev, cur, camera):
        seen["camera"] = camera
        return flow_pose(prev, cur, camera)

    odo.model.flow_pose = recorded
    for i in range(last + 1):
        odo.step(seq.image(i), seq.scan(i), float(seq.times[i]))
        if i < first:
            continue
        out, cam = odo.last["flowpose"], seen["camera"]
        true = change_frame(relative(gt.poses[i - 1], gt.poses[i]), odo.calib.T_cam2_cam0)
        err = lambda A: float(np.linalg.norm(relative(true, A)[:3, 3]))  # noqa: E731
        step = lambda A: float(np.linalg.norm(A[:3, 3]))  # noqa: E731
        kept, weighted = out["matrix"][0].astype(np.float64), out["start_next"][0].astype(np.float64)
        start = cam["init_pose"][0].astype(np.float64)
        # the classical pose is an input where the model solves it beside (two threads), else inside the graph
        classical = cam["classical_pose"][0].astype(np.float64) if "classical_pose" in cam else None
        w = out["point_weights"][0]
        print(f"pair {i}: true {step(true):.3f}  kept {step(kept):.3f} (off {err(kept):.3f})  weighted "
              f"{step(weighted):.3f} (off {err(weighted):.3f})  classical "
              + (f"{step(classical):.3f} (off {err(classical):.3f})" if classical is not None else "(in the graph)")
              + f"  start off {err(start):.3f}  distrusted {np.mean(w[w > 0] < 0.5):.2f}")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    try:
        main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))
    except D3LVOInputError as e:
        sys.exit(f"error: {e}")
    except ValueError:
        sys.exit(__doc__)
