"""The three deployment stages as modules with flat, named tensor inputs and outputs.

Splitting at these points lets the runtime complete and encode each frame exactly once and
reuse frame t's encoder outputs as frame t-1 of the next pair.
"""

from __future__ import annotations

from torch import nn

from models.d3lvo import D3LVO


def encoder_output_names(model: D3LVO) -> list[str]:
    names = [f"feat_l{lvl}" for lvl in model.cfg.flow_levels]
    if model.cfg.uses_depth:
        names += [f"invdepth_l{lvl}" for lvl in model.cfg.flow_levels]
    return names


def flowpose_input_names(model: D3LVO) -> list[str]:
    lv = model.cfg.flow_levels
    names = [f"feat1_l{lvl}" for lvl in lv] + [f"feat2_l{lvl}" for lvl in lv]
    if model.cfg.uses_depth:
        names += [f"invdepth1_l{lvl}" for lvl in lv]
    return names


def flowpose_output_names(model: D3LVO) -> list[str]:
    return [f"flow_l{lvl}" for lvl in model.cfg.flow_levels] + ["level_poses", "level_weights", "pose", "matrix"]


class CompletionStage(nn.Module):
    """rgb (B,3,H,W) in [0,1], sparse_depth (B,1,H,W) metres -> dense_depth (B,1,H,W) metres."""

    input_names = ["rgb", "sparse_depth"]
    output_names = ["dense_depth"]

    def __init__(self, model: D3LVO):
        super().__init__()
        self.model = model

    def forward(self, rgb, sparse_depth):
        return self.model.complete(rgb, sparse_depth)


class EncoderStage(nn.Module):
    """rgb (+ depth) -> the pyramid levels the flow uses, and depth at those levels."""

    def __init__(self, model: D3LVO):
        super().__init__()
        self.model = model
        self.input_names = ["rgb", "depth"] if model.cfg.uses_depth else ["rgb"]
        self.output_names = encoder_output_names(model)

    def forward(self, rgb, depth=None):
        feats, depths = self.model.encode(rgb, depth)
        lv = self.model.cfg.flow_levels
        out = [feats[lvl] for lvl in lv]
        if self.model.cfg.uses_depth:
            out += [depths[lvl] for lvl in lv]
        return tuple(out)


class FlowPoseStage(nn.Module):
    """Both frames' pyramids (+ frame t-1 depth) -> flows, per-level poses and weights, final pose."""

    def __init__(self, model: D3LVO):
        super().__init__()
        self.model = model
        self.input_names = flowpose_input_names(model)
        self.output_names = flowpose_output_names(model)

    def forward(self, *tensors):
        lv = self.model.cfg.flow_levels
        n = len(lv)
        f1, f2, d1 = [None] * 4, [None] * 4, [None] * 4
        for i, lvl in enumerate(lv):
            f1[lvl], f2[lvl] = tensors[i], tensors[n + i]
            if self.model.cfg.uses_depth:
                d1[lvl] = tensors[2 * n + i]
        out = self.model.flow_pose(f1, f2, d1)
        return (*out["flows"], out["poses"], out["weights"], out["pose"], out["matrix"])
