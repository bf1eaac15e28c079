"""The deployment stages as modules with flat, named tensor inputs and outputs.

Splitting at these points lets the runtime complete and encode each frame exactly once and
reuse frame t's encoder outputs as frame t-1 of the next pair. A point-solver model that also
solves its classical mode (`pt_select`) gets two more: that solve alone (`classical`), which reads
no network output and so runs on a core of its own beside completion and encoder, and the flow+pose
graph that takes its pose (`flowpose_weighted`). The stages exchange what the
network computes with: ImageNet-normalised RGB (`rgb_norm`) and inverse depth (min_depth / d,
0 = no return), made by the runtime's preprocessing in the same pass that crops the image and
projects the scan (d3lvo_deploy.frames.FramePreprocessor.rgb_input / invdepth_input).
"""

from __future__ import annotations

from torch import nn

from d3lvo_deploy.points import CLASSICAL_INPUT, CLASSICAL_NEXT_OUTPUT, CLASSICAL_START_INPUT, SCAN_DEPTH_INPUT
from d3lvo_deploy.selection import SELECT_KEPT_OUTPUT
from models.d3lvo import D3LVO
from models.point_solver import pyramid_input_names


# inputs of the flow+pose graph that are not encoder outputs (Gauss-Newton head only): the camera
# (fx, fy, cx, cy at the network input, (B,4)) and the starting relative pose ((B,4,4), the
# previous pair's motion at run time)
CAMERA_INPUTS = ("intrinsics", "init_pose")
# and the point solver's (pose_head="points"): both frames' image pyramids at the camera's resolution
# (frame t-1's grey, frame t's grey and derivatives; heights and widths dynamic; their names from
# `point_solver.pyramid_input_names`), frame t-1's LiDAR point list with its mask, image_2's intrinsics
SOLVER_INPUTS = ("points1", "point_mask1", "image_intrinsics")


def solver_input_names(model: D3LVO, scan: bool | None = None) -> list[str]:
    """The point solver's inputs; frame t's scan where the graph reads it (`scan`: default the
    flow+pose graph's `reads_scan`)."""
    grey1, stack2 = pyramid_input_names(len(model.cfg.pt_iters))
    scan = model.cfg.reads_scan if scan is None else scan
    return grey1 + stack2 + list(SOLVER_INPUTS) + ([SCAN_DEPTH_INPUT] if scan else [])


def splits_classical(model: D3LVO) -> bool:
    """The model solves its classical mode beside the weighted solve: export `classical` and
    `flowpose_weighted` too."""
    return model.cfg.point_solver and model.cfg.pt_select > 0


def classical_input_names(model: D3LVO) -> list[str]:
    """The classical solve reads frame t's scan for the restart's check and the scan gate only
    (not for judging between the two poses, which the weighted graph does)."""
    cfg = model.cfg
    return solver_input_names(model, cfg.checks_restart_on_scan or cfg.gates_on_scan) + ["init_pose"]


def encoder_output_names(model: D3LVO) -> list[str]:
    cfg = model.cfg
    names = [f"feat_l{lvl}" for lvl in cfg.flow_levels]
    if cfg.uses_depth:
        names += [f"invdepth_l{lvl}" for lvl in cfg.depth_levels]
    names += [f"grey_l{lvl}" for lvl in cfg.gn_levels]
    if cfg.gn_lidar:
        names += [f"lidar_l{lvl}" for lvl in cfg.gn_levels]
    return names


def flowpose_input_names(model: D3LVO) -> list[str]:
    cfg = model.cfg
    lv = cfg.flow_levels
    names = [f"feat1_l{lvl}" for lvl in lv] + [f"feat2_l{lvl}" for lvl in lv]
    if cfg.uses_depth:
        names += [f"invdepth1_l{lvl}" for lvl in cfg.depth_levels]
    names += [f"grey1_l{lvl}" for lvl in cfg.gn_levels] + [f"grey2_l{lvl}" for lvl in cfg.gn_levels]
    if cfg.gn_lidar:
        names += [f"lidar1_l{lvl}" for lvl in cfg.gn_levels]
    if cfg.point_solver:  # frame t's depth too: the confidence compares it with the start's prediction
        return names + [f"invdepth2_l{cfg.flow_levels[-1]}"] + list(CAMERA_INPUTS) + solver_input_names(model)
    return names + (list(CAMERA_INPUTS) if cfg.geometric else [])


def flowpose_output_names(model: D3LVO) -> list[str]:
    cfg = model.cfg
    conf = [f"confidence_l{cfg.flow_levels[-1]}", "point_weights"] if cfg.point_solver else \
        [f"confidence_l{lvl}" for lvl in cfg.gn_levels]
    start = ["start_next"] if cfg.point_solver and cfg.pt_select > 0 else []
    if cfg.pt_classical_chain:  # the config allows it only beside `start_next`
        start.append(CLASSICAL_NEXT_OUTPUT)
    if cfg.pt_select_hold:  # likewise: which pose the choice kept, for the runtime's hold
        start.append(SELECT_KEPT_OUTPUT)
    return [f"flow_l{lvl}" for lvl in cfg.flow_levels] + conf + ["level_poses", "level_weights", "pose", "matrix"] + start


class CompletionStage(nn.Module):
    """rgb_norm (B,3,H,W), sparse_invdepth (B,1,H,W) -> dense_invdepth (B,1,H,W) in [min/max depth, 1]."""

    input_names = ["rgb_norm", "sparse_invdepth"]
    output_names = ["dense_invdepth"]

    def __init__(self, model: D3LVO):
        super().__init__()
        self.model = model

    def forward(self, rgb_norm, sparse_invdepth):
        return self.model.complete_inverse(rgb_norm, sparse_invdepth)


class EncoderStage(nn.Module):
    """rgb_norm (+ invdepth) -> the pyramid levels the flow uses, and inverse depth at those levels."""

    def __init__(self, model: D3LVO):
        super().__init__()
        self.model = model
        self.input_names = ["rgb_norm", "invdepth"] if model.cfg.uses_depth else ["rgb_norm"]
        if model.cfg.gn_lidar:
            self.input_names.append("sparse_invdepth")  # the LiDAR returns, before completion
        self.output_names = encoder_output_names(model)

    def forward(self, rgb_norm, invdepth=None, sparse_invdepth=None):
        cfg = self.model.cfg
        feats, depths, greys = self.model.encode_inverse(rgb_norm, invdepth)
        out = [feats[lvl] for lvl in cfg.flow_levels]
        if cfg.uses_depth:
            out += [depths[lvl] for lvl in cfg.depth_levels]
        out += [greys[lvl] for lvl in cfg.gn_levels]
        if cfg.gn_lidar:
            lidar = self.model.lidar_levels(sparse_invdepth)
            out += [lidar[lvl] for lvl in cfg.gn_levels]
        return tuple(out)


class FlowPoseStage(nn.Module):
    """Both frames' pyramids (+ frame t-1 depth) -> flows, per-level poses and weights, final pose.
    `weighted`: the classical mode's pose is an input (`ClassicalStage`'s output) rather than
    solved here; the outputs are the same."""

    def __init__(self, model: D3LVO, weighted: bool = False):
        super().__init__()
        self.model = model
        # the classical pose given, or (`pt_classical_chain`) where its solve starts
        self.input_names = flowpose_input_names(model) + ([CLASSICAL_INPUT] if weighted else
                                                          [CLASSICAL_START_INPUT] if model.cfg.pt_classical_chain
                                                          else [])
        self.output_names = flowpose_output_names(model)

    def forward(self, *tensors):
        byname = dict(zip(self.input_names, tensors))
        levels = lambda prefix: [byname.get(f"{prefix}_l{lvl}") for lvl in range(4)]  # noqa: E731
        solver = None
        if self.model.cfg.point_solver:
            given = [n for n in (CLASSICAL_INPUT, CLASSICAL_START_INPUT) if n in byname]
            names = solver_input_names(self.model) + given
            solver = {k: byname[k] for k in names}
        out = self.model.flow_pose(levels("feat1"), levels("feat2"), levels("invdepth1"), levels("grey1"),
                                   levels("grey2"), byname.get("intrinsics"), byname.get("init_pose"),
                                   levels("lidar1") if self.model.cfg.gn_lidar else None, solver, levels("invdepth2"))
        extra = [out["point_weights"]] if "point_weights" in out else []
        start = [out[n] for n in ("start_next", CLASSICAL_NEXT_OUTPUT, SELECT_KEPT_OUTPUT) if n in out]
        return (*out["flows"], *out.get("confidence", []), *extra, out["poses"], out["weights"], out["pose"],
                out["matrix"], *start)


class ClassicalStage(nn.Module):
    """The solver's inputs and the start (`init_pose`) -> the classical mode's pose (`CLASSICAL_INPUT`,
    (B,4,4) frame t in frame t-1): `PointPose.classical_solve`."""

    output_names = [CLASSICAL_INPUT]

    def __init__(self, model: D3LVO):
        super().__init__()
        self.model = model
        self.input_names = classical_input_names(model)

    def forward(self, *tensors):
        byname = dict(zip(self.input_names, tensors))
        solver = {k: byname[k] for k in self.input_names[:-1]}
        return self.model.point_pose.classical_solve(solver, byname["init_pose"])
