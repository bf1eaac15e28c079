"""Torch latency (eager or torch.compile) of the same three stages, for `d3lvo bench`'s engine/torch comparison.

Speed does not depend on weight values, so the model is built from the export's config.
"""

from __future__ import annotations

import numpy as np
import torch

from d3lvo_deploy.bench import bench_frames, timed
from d3lvo_deploy.frames import FramePreprocessor
from d3lvo_deploy.odometry import clean_scan
from d3lvo_deploy.points import SolverFrame, point_config, solver_feeds
from d3lvo_deploy.sequence import KittiSequence

from .config import D3LVOConfig
from .d3lvo import D3LVO


class TorchStream:
    """The three stages in torch, one frame per call, so that `take_turns` can time them beside
    the engines. Each frame is preprocessed from its image and scan inside the call, as the ONNX
    pipeline does, so both sides' stage times are taken under the same conditions (caches, idle
    cores). `compile`: the stages through torch.compile (inductor), compiled by the warm-up frames."""

    def __init__(self, cfg: D3LVOConfig, seq: KittiSequence, threads: int, compile: bool = False,
                 frames: list | None = None):
        if threads > 0:
            torch.set_num_threads(threads)
        self.cfg, self.calib = cfg, seq.calib
        self.model = model = D3LVO(cfg).eval()
        stages = (model.complete_inverse, model.encode_inverse, model.flow_pose)
        self.complete, self.encode, self.flow_pose = (torch.compile(f) for f in stages) if compile else stages
        # the first calls compile; the second pair is the first steady one
        self.warmup = 3 if compile else 2
        self.raw = frames if frames is not None else bench_frames(seq)
        h, w = self.raw[0][0].shape[:2]
        self.pre = pre = FramePreprocessor.for_model(seq.calib, w, h, cfg.to_dict(), cfg.depth_input)
        # the point head's solver inputs (points, image pyramids), made outside the timing as the
        # ONNX side's `project` stage makes them
        self.solvers = [SolverFrame.of(image, clean_scan(scan), seq.calib.T_cam2_velo, seq.calib.K2,
                                       point_config(cfg.to_dict()), len(cfg.pt_iters),
                                       seq.calib.P_velo_to_image2 if cfg.reads_scan else None)
                        for image, scan in self.raw] \
            if cfg.point_solver else None
        self.K = torch.tensor([[pre.K[0, 0], pre.K[1, 1], pre.K[0, 2], pre.K[1, 2]]], dtype=torch.float32)
        self.k, self.prev = 0, None

    @torch.no_grad()
    def __call__(self) -> dict[str, float]:
        cfg, k, n = self.cfg, self.k, len(self.raw)
        image, scan = self.raw[k % n]
        rgb = torch.from_numpy(self.pre.rgb_input(image))
        inv = self.pre.invdepth_input(scan if cfg.uses_depth else None)
        inv = None if inv is None else torch.from_numpy(inv)
        ms: dict[str, float] = {}
        box: dict = {}
        # the deployed forms (normalised RGB, inverse depth), as the ONNX stages get them
        ms["completion"] = timed(lambda: box.__setitem__("d", self.complete(rgb, inv) if inv is not None else None))
        ms["encoder"] = timed(lambda: box.__setitem__("e", (*self.encode(rgb, box["d"]), self.model.lidar_levels(inv))))
        cur, prev = box["e"], self.prev
        solver = None
        if self.solvers is not None and prev is not None:
            feeds = solver_feeds(self.solvers[(k - 1) % n], self.solvers[k % n], self.calib.K2, cfg.pt_capacity)
            solver = {name: torch.from_numpy(np.ascontiguousarray(v)) for name, v in feeds.items()}
        ms["flowpose"] = timed(lambda: self.flow_pose(prev[0], cur[0], prev[1], prev[2], cur[2], self.K, None, prev[3],
                                                      solver, cur[1])) if prev is not None else 0.0
        self.prev, self.k = cur, k + 1
        return ms

