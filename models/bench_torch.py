"""Torch-eager latency of the same three stages, for `d3lvo bench`'s ORT/torch comparison.

Speed does not depend on weight values, so the model is built from the export's config.
"""

from __future__ import annotations

import torch

from d3lvo_deploy.bench import StageTimes, timed
from d3lvo_deploy.frames import FramePreprocessor
from d3lvo_deploy.sequence import KittiSequence

from .config import D3LVOConfig
from .d3lvo import D3LVO


@torch.no_grad()
def bench_torch(cfg: D3LVOConfig, seq: KittiSequence, threads: int, runs: int, warmup: int = 2) -> StageTimes:
    """Each frame is preprocessed from its image and scan inside the loop, as the ONNX pipeline
    does, so both sides' stage times are taken under the same conditions (caches, idle cores)."""
    if threads > 0:
        torch.set_num_threads(threads)
    model = D3LVO(cfg).eval()
    h, w = seq.image(0).shape[:2]
    pre = FramePreprocessor.create(seq.calib, w, h, cfg.width, cfg.height, cfg.depth_input, cfg.max_depth)
    raw = [(seq.image(i), seq.scan(i)) for i in range(min(len(seq), 10))]
    times = StageTimes()
    prev = None
    for k in range(warmup + runs):
        image, scan = raw[k % len(raw)]
        rgb = torch.from_numpy(pre.rgb_nchw(image))
        depth = torch.from_numpy(pre.depth(scan if cfg.uses_depth else None)[None, None])
        ms: dict[str, float] = {}
        box: dict = {}
        ms["completion"] = timed(lambda: box.__setitem__("d", model.complete(rgb, depth) if cfg.uses_depth else None))
        ms["encoder"] = timed(lambda: box.__setitem__("e", model.encode(rgb, box["d"])))
        cur = box["e"]
        ms["flowpose"] = timed(lambda: model.flow_pose(prev[0], cur[0], prev[1])) if prev is not None else 0.0
        prev = cur
        if k >= warmup:
            times.add(ms)
    return times
