"""Choose `pt_select` and `pt_select_rotation` on validation drives.

    python scripts/selection_rules.py [--ckpt CKPT] DRIVE...

Runs the checkpoint once per drive (torch, one thread) and records, per pair, the weighted and the
classical solve's poses and the consensus gain. Each pair starts from the weighted pose whatever is
kept, so every rule's trajectory is the recorded poses chosen pair by pair: the grid below is
scored without running the network again. Prints, per rule, each drive's t_rel % (ATE m, marked
`ate`, for drives under 100 m), and the sums the choice reads: on static drives the difference
to the classical pose kept always, on drives with traffic (a `synth.json` with traffic above 0)
the mean and the smallest reduction against it. Beside the grid, at the shipped thresholds, two
rules that do not ship: a cap on the share of frame t-1's points the network distrusts, and the
test passed on the previous pair too (a mover stays in view for several pairs).
"""

from __future__ import annotations

import itertools
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.evaluation import evaluate
from d3lvo_deploy.geometry import accumulate, change_frame, rotation_angle_precise
from d3lvo_deploy.poses import Trajectory, read_poses
from d3lvo_deploy.sequence import KittiSequence
from d3lvo_deploy.synth.generator import drive_traffic
from models import pose_points
from models.checkpoint import build_model, load_checkpoint
from models.predict import predict_sequence

GAINS = (0.003, 0.005, 0.0075, 0.01, 0.02)
ROTATIONS = (0.0, 0.04, 0.05, 0.06, 0.08, 0.1)  # degrees; 0: off
SHIPPED = (0.005, 0.05)
SHARES = (0.8, 0.7, 0.6, 0.5)  # the most of frame t-1's points the network may distrust


def distrusted_share(weight: torch.Tensor, mask: torch.Tensor) -> float:
    """The share of frame t-1's points (mask above 0) the network distrusts (weight under 0.5,
    where `consensus_gain`'s trusted points begin): batch row 0."""
    valid = (mask[0] > 0).to(weight.dtype)
    return float((valid * (weight[0] < 0.5).to(weight.dtype)).sum() / valid.sum().clamp(min=1.0))


def record_pairs(model, drive: str) -> list[dict]:
    """Per pair: gain, weighted pose W and classical pose C (image_2, frame t in frame t-1), the
    share of the points the network distrusts."""
    pairs: list[dict] = []
    forward = pose_points.PointPose.forward

    def recording(self, *args):
        out = forward(self, *args)
        if "consensus_gain" in out:
            pairs.append(dict(gain=float(out["consensus_gain"][0]), W=out["start_next"][0].double().numpy(),
                              C=out["classical"][0].double().numpy(),
                              share=distrusted_share(out["point_weights"], args[-1]["point_mask1"])))
        return out

    pose_points.PointPose.forward = recording
    try:
        predict_sequence(model, drive)
    finally:
        pose_points.PointPose.forward = forward
    return pairs


@dataclass
class Drive:
    """What scoring a drive reads from its folder, read once for every rule."""
    T_cam0_cam2: np.ndarray
    gt: Trajectory
    traffic: bool

    @classmethod
    def open(cls, drive: str) -> "Drive":
        return cls(KittiSequence.open(drive).calib.T_cam0_cam2, read_poses(Path(drive) / "poses.txt"),
                   (drive_traffic(drive) or 0) > 0)


def score(drive: Drive, relatives: list[np.ndarray]) -> tuple[float, str]:
    rel = np.array([change_frame(A, drive.T_cam0_cam2) for A in relatives])
    r = evaluate(drive.gt, Trajectory.from_poses(accumulate(rel)))
    return (r.t_rel, "") if r.t_rel is not None else (r.ate, " ate")


def main(drives: list[str], checkpoint: Path) -> None:
    for drive in drives:
        if not (Path(drive) / "poses.txt").is_file():
            sys.exit(f"{drive}: no poses.txt, the ground truth this script scores against")
    torch.set_num_threads(1)
    ck = load_checkpoint(checkpoint)
    ck["config"] = replace(ck["config"], pt_select=min(GAINS), pt_select_rotation=0.0)  # both solves, every pair
    model = build_model(ck)
    pairs = {}
    for drive in drives:
        pairs[drive] = record_pairs(model, drive)
        for p in pairs[drive]:
            D = p["C"][:3, :3].T @ p["W"][:3, :3]
            p["rotation"] = float(np.degrees(rotation_angle_precise(D)))
        print(f"recorded {Path(drive).name}: {len(pairs[drive])} pairs", flush=True)
    info = {d: Drive.open(d) for d in drives}
    classical = {d: score(info[d], [p["C"] for p in pairs[d]])[0] for d in drives}

    def test(g: float, r: float):
        return lambda ps, i: ps[i]["gain"] > g and ps[i]["rotation"] > r

    rules = [("classical always", lambda ps, i: False), ("weighted always", lambda ps, i: True)]
    rules += [(f"pt_select {g} pt_select_rotation {r}", test(g, r)) for g, r in itertools.product(GAINS, ROTATIONS)]
    shipped = test(*SHIPPED)
    rules += [(f"shipped, distrusted share <= {f}", lambda ps, i, f=f: shipped(ps, i) and ps[i]["share"] <= f)
              for f in SHARES]
    rules.append(("shipped, passed on the last pair too",
                  lambda ps, i: shipped(ps, i) and i > 0 and shipped(ps, i - 1)))
    print("drives: " + " ".join(Path(d).name for d in drives))
    for name, keep in rules:
        scores = {d: score(info[d], [p["W"] if keep(pairs[d], i) else p["C"] for i, p in enumerate(pairs[d])])
                  for d in drives}
        static = [scores[d][0] - classical[d] for d in drives if not info[d].traffic]
        cut = [1 - scores[d][0] / classical[d] for d in drives if info[d].traffic]
        summary = f"static: sum {sum(static):+.4f}, higher on {sum(x > 1e-4 for x in static)}, lower on " \
                  f"{sum(x < -1e-4 for x in static)}" if static else ""
        if cut:
            summary += f"; traffic: cut mean {100 * np.mean(cut):.1f} %, smallest {100 * min(cut):.1f} %"
        print(f"{name:42s} {summary} | " + " ".join(f"{s:.3f}{unit}" for s, unit in scores.values()), flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    ckpt = bundled_model_dir() / "default.pt"
    if args[:1] == ["--ckpt"] and len(args) > 1:
        ckpt, args = Path(args[1]), args[2:]
    if not args:
        sys.exit(__doc__)
    if not ckpt.is_file():
        sys.exit(f"{ckpt}: no such checkpoint")
    main(args, ckpt)
