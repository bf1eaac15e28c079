"""Run the torch model over a sequence: validation during training and the reference for parity."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from d3lvo_deploy.cold_start import ColdStartConfig
from d3lvo_deploy.geometry import accumulate, change_frame
from d3lvo_deploy.odometry import cold_start_motion
from d3lvo_deploy.points import CLASSICAL_NEXT_OUTPUT, CLASSICAL_START_INPUT, solver_feeds
from d3lvo_deploy.selection import SELECT_KEPT_OUTPUT, held_pose
from d3lvo_deploy.sequence import KittiSequence

from .data import FrameLoader
from .layers import inverse_depth


@torch.no_grad()
def predict_sequence(model, seq_dir: str | Path, start: int = 0, end: int | None = None,
                     cold_start: ColdStartConfig = ColdStartConfig()) -> np.ndarray:
    """(N,4,4) cam0 poses, first identity; each frame is completed and encoded exactly once. The
    first pair of a point-solver model starts from `cold_start`'s guesses, as at run time."""
    model.eval()
    seq = KittiSequence.open(seq_dir)
    loader = FrameLoader(seq, model.cfg)
    end = len(seq) if end is None else end
    dev = next(model.parameters()).device
    K = torch.tensor([[loader.K[0, 0], loader.K[1, 1], loader.K[0, 2], loader.K[1, 2]]], dtype=torch.float32,
                     device=dev)
    prev = solver_prev = None
    motion = torch.eye(4, device=dev)[None]  # image_2 motion of the previous pair: the GN head's start
    classical = None  # `pt_classical_chain`: the previous classical pose, the classical solve's start
    hold_left = 0  # `pt_select_hold`: pairs left on which the weighted pose is kept (the runtime's `held_pose`)
    rel = []
    for i in range(start, end):
        rgb = torch.from_numpy(loader.rgb(i)).permute(2, 0, 1)[None].to(dev)
        depth = torch.from_numpy(loader.depth_input(i))[None, None].to(dev)
        dense = model.complete(rgb, depth) if model.cfg.uses_depth else None
        cur = (*model.encode(rgb, dense), model.lidar_levels(inverse_depth(depth, model.cfg.min_depth)))
        solver_cur = loader.solver_frame(i, model.cfg.reads_scan) if model.cfg.point_solver else None
        if prev is not None:
            solver = None
            if solver_cur is not None:
                feeds = solver_feeds(solver_prev, solver_cur, seq.calib.K2, model.cfg.pt_capacity)
                solver = {k: torch.from_numpy(np.ascontiguousarray(v)).to(dev) for k, v in feeds.items()}
            if solver is not None and not rel and len(solver_prev.points):  # the first pair: no previous motion
                A = cold_start_motion(solver_prev, solver_cur, seq.calib.K2, model.cfg.to_dict(), cold_start)
                motion = torch.tensor(A, dtype=torch.float32, device=dev)[None]
            if solver is not None and model.cfg.pt_classical_chain:
                solver[CLASSICAL_START_INPUT] = motion if classical is None else classical
            out = model.flow_pose(prev[0], cur[0], prev[1], prev[2], cur[2], K, motion, prev[3], solver, cur[1])
            A2 = out["matrix"][0].double().cpu().numpy()
            if model.cfg.pt_select_hold:
                kept = {k: out[k].double().cpu().numpy() for k in ("matrix", "start_next", SELECT_KEPT_OUTPUT)}
                A2, hold_left = held_pose(kept, hold_left, model.cfg.pt_select_hold)
            motion = out.get("start_next", out["matrix"])  # the next pair's start (`pt_select`: the weighted pose)
            classical = out.get(CLASSICAL_NEXT_OUTPUT)
            rel.append(change_frame(A2, seq.calib.T_cam0_cam2))
        prev, solver_prev = cur, solver_cur
    return accumulate(np.array(rel).reshape(-1, 4, 4))
