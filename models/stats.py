"""Parameter counts and forward FLOPs per deployment stage (`python -m models.stats`)."""

from __future__ import annotations

import torch
from torch.utils.flop_counter import FlopCounterMode

from .config import D3LVOConfig
from .d3lvo import D3LVO
from .layers import inverse_depth


def _count(fn) -> int:
    with FlopCounterMode(display=False) as fc:
        fn()
    return fc.get_total_flops()


@torch.no_grad()
def stage_stats(cfg: D3LVOConfig) -> dict[str, dict[str, float]]:
    """Per stage: parameters and GFLOPs (2 x multiply-adds) for one frame / one pair at cfg's size."""
    model = D3LVO(cfg).eval()
    rgb = torch.rand(1, 3, cfg.height, cfg.width)
    sparse = torch.rand(1, 1, cfg.height, cfg.width) * 50 * (torch.rand(1, 1, cfg.height, cfg.width) > 0.95)
    dense = model.complete(rgb, sparse) if cfg.uses_depth else None
    feats, depths, greys = model.encode(rgb, dense)
    lidar = model.lidar_levels(inverse_depth(sparse, cfg.min_depth))
    params = lambda m: sum(p.numel() for p in m.parameters()) if m is not None else 0  # noqa: E731
    flow_params = params(model.flow) + params(model.pose) + params(model.context) + params(model.gn_pose)
    out = {
        "completion": {"params": params(model.completion),
                       "gflops": _count(lambda: model.complete(rgb, sparse)) / 1e9 if model.completion else 0.0},
        "encoder": {"params": params(model.encoder), "gflops": _count(lambda: model.encode(rgb, dense)) / 1e9},
        "flowpose": {"params": flow_params, "gflops": _count(lambda: model.flow_pose(feats, feats, depths, greys, greys, lidar1=lidar)) / 1e9},
    }
    out["total"] = {"params": sum(v["params"] for v in out.values()), "gflops": sum(v["gflops"] for v in out.values())}
    return out


if __name__ == "__main__":
    for name, cfg in (("default 1216x352", D3LVOConfig()), ("small 608x176", D3LVOConfig.small()),
                      ("paper 1216x352", D3LVOConfig.paper())):
        print(name)
        for stage, v in stage_stats(cfg).items():
            print(f"  {stage:10s} {v['params'] / 1e6:6.3f} M params  {v['gflops']:7.2f} GFLOPs")
