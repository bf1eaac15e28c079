"""Torch-eager latency of the same three stages, for `d3lvo bench`'s ORT/torch comparison.

Speed does not depend on weight values, so the model is built from the export's config.
"""

from __future__ import annotations

import numpy as np
import torch

from d3lvo_deploy.bench import StageTimes, timed
from d3lvo_deploy.frames import FramePreprocessor
from d3lvo_deploy.odometry import clean_scan
from d3lvo_deploy.points import SolverFrame, point_config, solver_feeds
from d3lvo_deploy.sequence import KittiSequence

from .config import D3LVOConfig
from .d3lvo import D3LVO


@torch.no_grad()
def bench_torch(cfg: D3LVOConfig, seq: KittiSequence, threads: int, runs: int, warmup: int = 2,
                compile: bool = False) -> StageTimes:
    """Each frame is preprocessed from its image and scan inside the loop, as the ONNX pipeline
    does, so both sides' stage times are taken under the same conditions (caches, idle cores).
    `compile`: the three stages through torch.compile (inductor), compiled during the warm-up."""
    if threads > 0:
        torch.set_num_threads(threads)
    model = D3LVO(cfg).eval()
    complete, encode, flow_pose = model.complete_inverse, model.encode_inverse, model.flow_pose
    if compile:
        complete, encode, flow_pose = (torch.compile(f) for f in (complete, encode, flow_pose))
        warmup = max(warmup, 3)  # the first calls compile; the second pair is the first steady one
    h, w = seq.image(0).shape[:2]
    pre = FramePreprocessor.for_model(seq.calib, w, h, cfg.to_dict(), cfg.depth_input)
    raw = [(seq.image(i), seq.scan(i)) for i in range(min(len(seq), 10))]
    # the point head's solver inputs (points, image pyramids), made outside the timing as the
    # ONNX side's `project` stage makes them
    solvers = [SolverFrame.of(image, clean_scan(scan), seq.calib.T_cam2_velo, seq.calib.K2,
                              point_config(cfg.to_dict()), len(cfg.pt_iters)) for image, scan in raw] \
        if cfg.point_solver else None
    K = torch.tensor([[pre.K[0, 0], pre.K[1, 1], pre.K[0, 2], pre.K[1, 2]]], dtype=torch.float32)
    times = StageTimes()
    prev = None
    for k in range(warmup + runs):
        image, scan = raw[k % len(raw)]
        rgb = torch.from_numpy(pre.rgb_input(image))
        inv = pre.invdepth_input(scan if cfg.uses_depth else None)
        inv = None if inv is None else torch.from_numpy(inv)
        ms: dict[str, float] = {}
        box: dict = {}
        # the deployed forms (normalised RGB, inverse depth), as the ONNX stages get them
        ms["completion"] = timed(lambda: box.__setitem__("d", complete(rgb, inv) if inv is not None else None))
        ms["encoder"] = timed(lambda: box.__setitem__("e", (*encode(rgb, box["d"]), model.lidar_levels(inv))))
        cur = box["e"]
        solver = None
        if solvers is not None and prev is not None:
            feeds = solver_feeds(solvers[(k - 1) % len(raw)], solvers[k % len(raw)], seq.calib.K2, cfg.pt_capacity)
            solver = {n: torch.from_numpy(np.ascontiguousarray(v)) for n, v in feeds.items()}
        ms["flowpose"] = timed(lambda: flow_pose(prev[0], cur[0], prev[1], prev[2], cur[2], K, None, prev[3], solver,
                                                 cur[1])) if prev is not None else 0.0
        prev = cur
        if k >= warmup:
            times.add(ms)
    return times
