"""`python -m models.pair_eval CKPT SEQ [SEQ ...]`: a checkpoint's frame-pair errors beside their
baselines on held-out sequences (flow EPE against zero flow per level, rotation against no
rotation, translation against no motion), the numbers "the flow is learned" and "it predicts
rotation" rest on. Same function as the training's validation (`models.train.pair_metrics`).

`--split-moving`: where the confidence misses what moves instead (`moving_auroc_split`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.metrics import auroc

from .checkpoint import build_model, load_checkpoint
from .d3lvo import D3LVO
from .data import PairDataset, rigid_flow
from .train import cell_pool, pair_metrics

# the moving cells' groups (name, from, to), in cells: how far a cell moves against the ego
# motion's rigid flow ([from, to)), and how far it lies from the nearest static cell ((from, to])
VISIBLE = (("visible_below_0.5", 0.0, 0.5), ("visible_0.5_to_2", 0.5, 2.0), ("visible_from_2", 2.0, np.inf))
INSIDE = (("edge_within_2", 0.0, 2.0), ("inside_2_to_5", 2.0, 5.0), ("inside_beyond_5", 5.0, np.inf))


@torch.no_grad()
def moving_cells(model: D3LVO, seq: str, pairs: int = 48) -> dict[str, np.ndarray]:
    """Per cell of the confidence's grid, over evenly spaced pairs of a drive rendered with `d3lvo
    synth --traffic`: `score` (1 - confidence, as `pair_metrics` ranks), `moving` (the motion
    mask's majority, as `pair_metrics`), `visible` (how far the cell moves against the rigid flow
    of the true ego motion on the renderer's depth: the true flow minus that, mean length over the
    cell's pixels where both are defined, in cells; a static cell's is 0) and `inside` (cells to the
    nearest static cell; 1 at a vehicle's edge); and per pixel of the network view, `pixel_score`
    (the confidence read at the pixel as the solver's points read it, `PointPose.point_confidence`)
    and `pixel_moving` (the motion mask)."""
    if not model.cfg.point_solver:
        raise D3LVOInputError(None, "--split-moving reads the point pose head's confidence; this model has "
                                    f"pose_head {model.cfg.pose_head!r}")
    missing = [f for f in ("motion_2", "flow_2", "depth_2") if not (Path(seq) / f).is_dir()]
    if missing:
        raise D3LVOInputError(seq, f"--split-moving needs {', '.join(f + '/' for f in missing)}, which a drive "
                                   "rendered with `d3lvo synth --traffic` has")
    model.eval()
    data = PairDataset([seq], model.cfg, augment=None)
    idx = np.linspace(0, len(data) - 1, min(pairs, len(data))).round().astype(int)
    cells: dict[str, list] = {"score": [], "moving": [], "visible": [], "inside": [], "pixel_score": [],
                              "pixel_moving": []}
    for i in idx:
        b = {k: v[None] for k, v in data[int(i)].items()}
        if float(b["moving"].min()) < 0:  # a frame without its motion mask: not scored, as `pair_metrics`
            continue
        out = model(b["rgb1"], b["rgb2"], b["depth1"], b["depth2"], b["K"], b["init"], data.solver_inputs(int(i)))
        c = out["confidence"][0]
        s = b["moving"].shape[-1] // c.shape[-1]
        moving = (cell_pool(b["moving"], s) > 0.5)[0, 0].numpy()
        fx, fy, cx, cy = b["K"][0].double().numpy()
        rigid, ok = rigid_flow(b["gt_depth1"][0, 0].numpy(), np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]),
                               b["matrix"][0].double().numpy())
        valid = ok[0] * b["flow_valid"][0, 0].numpy()
        apart = np.linalg.norm(b["flow"][0].numpy() - rigid, axis=0) * valid / s
        pooled = [cell_pool(torch.from_numpy(a).float()[None, None], s)[0, 0].numpy() for a in (apart, valid)]
        cells["score"].append(-c[0, 0].numpy())
        cells["moving"].append(moving)
        cells["visible"].append(pooled[0] / np.maximum(pooled[1], 1e-6))
        cells["inside"].append(cv2.distanceTransform(moving.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE))
        # every pixel of the view as a point at depth 1, read by the solver's own reading
        h, w = b["moving"].shape[-2:]
        v, u = torch.meshgrid(torch.arange(h, dtype=c.dtype), torch.arange(w, dtype=c.dtype), indexing="ij")
        at_pixels = torch.stack([(u - float(cx)) / float(fx), (v - float(cy)) / float(fy), torch.ones_like(u)], -1)
        pixel = model.point_pose.point_confidence(c, at_pixels.reshape(1, -1, 3), b["K"].to(c.dtype))
        cells["pixel_score"].append(-pixel[0].numpy())
        cells["pixel_moving"].append(b["moving"][0, 0].numpy() > 0.5)
    return {k: np.concatenate([a.ravel() for a in v]) for k, v in cells.items()}


def split_auroc(score: np.ndarray, moving: np.ndarray, visible: np.ndarray, inside: np.ndarray,
                pixel_score: np.ndarray | None = None, pixel_moving: np.ndarray | None = None) -> dict:
    """The AUROC of `score` for moving against static cells, and the same for each group of the
    moving cells (`VISIBLE`, `INSIDE`) against every static cell, with the group's share of the
    moving cells: which cells an AUROC below target misses. With pixel scores, also the AUROC for
    moving against static pixels."""
    moving = moving.astype(bool)
    res = {"moving_auroc": auroc(score, moving), "moving_share": float(moving.mean())}
    if pixel_score is not None:
        res["pixel_auroc"] = auroc(pixel_score, pixel_moving)
    groups = [(name, (visible >= lo) & (visible < hi)) for name, lo, hi in VISIBLE]
    groups += [(name, (inside > lo) & (inside <= hi)) for name, lo, hi in INSIDE]
    for name, where in groups:
        group = moving & where
        keep = group | ~moving
        res[name] = {"auroc": auroc(score[keep], moving[keep]), "share": float(group.sum() / max(moving.sum(), 1))}
    return res


def moving_auroc_split(model: D3LVO, seq: str, pairs: int = 48) -> dict:
    """`split_auroc` of a drive's `moving_cells`: a vehicle that keeps pace with the scene behind
    it gives little evidence, and an edge cell holds both a vehicle and what is behind it, across
    which the flow is smooth."""
    return split_auroc(**moving_cells(model, seq, pairs))


def main() -> None:
    ap = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("ckpt")
    ap.add_argument("seqs", nargs="+")
    ap.add_argument("--pairs", type=int, default=48, help="evenly spaced pairs per sequence")
    ap.add_argument("--split-moving", action="store_true",
                    help="the confidence's AUROC for moving cells by how far they visibly move and how far "
                         "inside a vehicle they lie")
    args = ap.parse_args()
    if args.pairs < 1:
        ap.error(f"--pairs must be at least 1, not {args.pairs}")
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))
    try:
        model = build_model(load_checkpoint(args.ckpt))
        for s in args.seqs:
            m = moving_auroc_split(model, s, args.pairs) if args.split_moving else pair_metrics(model, [s], pairs=args.pairs)
            print(json.dumps({"sequence": s, **_rounded(m)}))
    except D3LVOInputError as e:  # a missing checkpoint or drive: one line, as the d3lvo commands
        sys.exit(f"error: {e}")


def _rounded(m: dict) -> dict:
    return {k: _rounded(v) if isinstance(v, dict) else None if v is None else round(v, 4) for k, v in m.items()}


if __name__ == "__main__":
    main()
