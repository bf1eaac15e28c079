"""The whole D3LVO network, split into the three stages the runtime runs.

`complete` (RGB + sparse -> dense depth), `encode` (one frame -> pyramid; run once per frame and
cached), `flow_pose` (two pyramids -> flows, per-level poses, weights, final relative pose).
Training calls them with RGB in [0,1] and depth in metres; the exported graphs use the
`*_inverse` forms, whose inputs (normalised RGB, inverse depth) the runtime's preprocessing makes
in the same pass that crops the image and projects the scan.
The relative pose is T(t-1 -> t) of the image_2 camera: frame t's pose in frame t-1's coordinates.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d3lvo_deploy.selection import SELECT_KEPT_OUTPUT

from .completion import DepthCompletion
from .config import D3LVOConfig
from .encoder import PyramidEncoder
from .flow import ContextNet, FlowLevel, upsample_flow
from . import gauss_newton as gn
from .layers import inverse_depth
from .pose import IDENTITY, PoseLevel, normalise_pose, pose_to_matrix
from .pose_gn import GaussNewtonPose, nominal_intrinsics
from .pose_points import PointPose


class D3LVO(nn.Module):
    def __init__(self, cfg: D3LVOConfig):
        super().__init__()
        self.cfg = cfg
        self.completion = (
            DepthCompletion(cfg.completion_widths, cfg.min_depth, cfg.max_depth) if cfg.learned_completion else None
        )
        self.encoder = PyramidEncoder(cfg)
        self.flow = nn.ModuleDict()
        self.pose = nn.ModuleDict()
        for i, lvl in enumerate(cfg.flow_levels):
            ch = cfg.feature_widths[lvl]
            self.flow[str(lvl)] = FlowLevel(cfg, ch, coarsest=i == 0)
            if not (cfg.geometric or cfg.point_solver):
                self.pose[str(lvl)] = PoseLevel(cfg, cfg.flow_hidden[1] + 2 + (1 if cfg.uses_depth else 0))
        self.gn_pose = GaussNewtonPose(cfg) if cfg.geometric else None
        self.point_pose = PointPose(cfg) if cfg.point_solver else None
        finest = cfg.flow_levels[-1]
        self.context = ContextNet(cfg.flow_hidden[1] + 2, cfg.context_width) if cfg.context else None
        self.register_buffer("rgb_mean", torch.tensor(cfg.rgb_mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("rgb_std", torch.tensor(cfg.rgb_std).view(1, 3, 1, 1), persistent=False)
        self._finest = finest

    # -- stage 1 -------------------------------------------------------------------------------
    def normalise(self, rgb: torch.Tensor) -> torch.Tensor:
        """rgb in [0, 1] -> ImageNet-normalised."""
        return (rgb - self.rgb_mean) / self.rgb_std

    def complete(self, rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Dense depth (m) from RGB [0,1] and the depth input; identity for rgb_sparse / ipbasic."""
        if self.completion is None:
            return depth
        return self.completion(self.normalise(rgb), depth)

    def complete_inverse(self, rgb_norm: torch.Tensor, inv: torch.Tensor) -> torch.Tensor:
        """The deployed form: normalised RGB and inverse depth (min_depth / d) in, inverse depth out.
        Equal to inverse_depth(complete(rgb, depth)) up to float rounding."""
        if self.completion is None:
            return inv
        return self.completion.forward_inverse(rgb_norm, inv)

    # -- stage 2 -------------------------------------------------------------------------------
    def encode(self, rgb: torch.Tensor, depth: torch.Tensor | None):
        """-> (features, depths, grey images) per level; see PyramidEncoder."""
        inv = inverse_depth(depth, self.cfg.min_depth) if self.cfg.uses_depth else None
        return self.encode_inverse(self.normalise(rgb), inv)

    def encode_inverse(self, rgb_norm: torch.Tensor, inv: torch.Tensor | None):
        """The deployed form of `encode`: normalised RGB and inverse depth (None in rgb mode)."""
        feats, depths = self.encoder(rgb_norm, inv if self.cfg.uses_depth else None)
        return feats, depths, self.encoder.grey_pyramid(rgb_norm)

    def lidar_levels(self, sparse_inv: torch.Tensor | None) -> list[torch.Tensor | None]:
        """The LiDAR returns (inverse depth, 0 = none) at each Gauss-Newton level's cell centres
        (input pixel s*i, as `PyramidEncoder`), for the solver's back-projection; None where unused."""
        out: list[torch.Tensor | None] = []
        for lvl in range(4):
            s = 2 ** (lvl + 1)
            if not (self.cfg.gn_lidar and lvl in self.cfg.gn_levels):
                out.append(None)
            elif self.cfg.gn_lidar_pool == "nearest":  # the closest return within s/2 pixels of s*i
                out.append(F.max_pool2d(sparse_inv, kernel_size=s + 1, stride=s, padding=s // 2))
            else:
                out.append(sparse_inv[..., ::s, ::s])
        return out

    # -- stage 3 -------------------------------------------------------------------------------
    def flow_pose(self, feats1, feats2, depths1, grey1=None, grey2=None, K: torch.Tensor | None = None,
                  init: torch.Tensor | None = None, lidar1=None,
                  solver: dict | None = None, depths2=None) -> dict[str, torch.Tensor | list[torch.Tensor]]:
        """Two frames' encoder outputs -> flows, per-level and final relative pose.

        The Gauss-Newton head also takes K (B,4) fx, fy, cx, cy at the network input (default: a
        nominal KITTI-like camera) and init (B,4,4), the starting relative pose (identity by
        default; the runtime passes the previous frame's motion, a constant-velocity start);
        lidar1 (`lidar_levels` of frame t-1) are the cells it back-projects where `gn_lidar`.
        The point head (`pose_head="points"`) also takes frame t's depths (`depths2`) and `solver`
        (see PointPose.forward): without it (training) only flows and confidences are computed."""
        ref = feats1[self.cfg.flow_levels[0]]
        b = ref.shape[0]
        pose = torch.tensor(IDENTITY, dtype=ref.dtype, device=ref.device).expand(b, 7)
        flow = None
        flows, poses, confs = [], [], []
        hidden_by, flow_by = {}, {}
        for lvl in self.cfg.flow_levels:
            f1, f2 = feats1[lvl], feats2[lvl]
            d1 = depths1[lvl] if self.cfg.uses_depth else None
            flow_up = None if flow is None else upsample_flow(flow, f1.shape[-2:])
            flow, hidden = self.flow[str(lvl)](f1, f2, flow_up, d1)
            if self.context is not None and lvl == self._finest:
                flow = self.context(hidden, flow)
            flows.append(flow)
            hidden_by[lvl], flow_by[lvl] = hidden, flow
            if self.gn_pose is None and self.point_pose is None:
                x = torch.cat([hidden, flow / 10.0] + ([d1] if d1 is not None else []), 1)
                pose, conf = self.pose[str(lvl)](x, pose)
                poses.append(pose)
                confs.append(conf)
        out: dict = {"flows": flows}
        if self.gn_pose is not None or self.point_pose is not None:  # the solvers' camera and start
            K = nominal_intrinsics(self.cfg, b, ref.dtype).to(ref.device) if K is None else K
            init = torch.eye(4, dtype=ref.dtype, device=ref.device).expand(b, 4, 4) if init is None else init
        if self.point_pose is not None:
            f = self._finest
            res = self.point_pose(hidden, flow, feats1[f], feats2[f], depths1[f], depths2[f], K, init, solver)
            out.update({"confidence": res["confidence"], "moving_logits": res["moving_logits"]})
            if "level_matrices" not in res:
                return out
            out["point_weights"] = res["point_weights"]
            # eq. 10 with w = (0, .., 0, 1): the coarse levels start the finer ones; an average
            # would pull the pose toward their blurrier estimates
            levels = torch.stack([gn.matrix_to_pose(M) for M in res["level_matrices"]], 1)
            n = levels.shape[1]
            weights = torch.zeros_like(levels[..., 0]) + torch.tensor([0.0] * (n - 1) + [1.0], dtype=ref.dtype,
                                                                       device=ref.device)
            # the matrix is rebuilt from the unit quaternion: the runtime chains it into the next
            # pair's start, and float32 drift from a rotation would grow there frame after frame
            final = normalise_pose(levels[:, -1])
            out.update({"poses": levels, "weights": weights, "pose": final, "matrix": pose_to_matrix(final)})
            if "start_next" in res:  # `pt_select`: the weighted pose, the next pair's start
                out["start_next"] = pose_to_matrix(normalise_pose(gn.matrix_to_pose(res["start_next"])))
            if self.cfg.pt_classical_chain:  # the classical solve's next start
                out["classical_next"] = pose_to_matrix(normalise_pose(gn.matrix_to_pose(res["classical"])))
            if self.cfg.pt_select_hold:  # which pose the choice kept: the runtime holds the weighted one
                out[SELECT_KEPT_OUTPUT] = res["select_kept"]
            return out
        if self.gn_pose is None:
            levels = torch.stack(poses, 1)  # (B, L, 7)
            weights = torch.softmax(torch.cat(confs, 1), dim=1)  # (B, L)
        else:
            points = lidar1 if self.cfg.gn_lidar else depths1
            if points is None:
                raise ValueError("this model's solver back-projects the LiDAR returns: pass lidar1=lidar_levels(...)")
            levels, weights, maps = self.gn_pose(hidden_by, flow_by, feats1, feats2, grey1, grey2, points, K, init)
            out["confidence"] = [maps[lvl] for lvl in self.cfg.gn_levels]
        final = normalise_pose((weights.unsqueeze(-1) * levels).sum(1))
        out.update({"poses": levels, "weights": weights, "pose": final, "matrix": pose_to_matrix(final)})
        return out

    def forward(self, rgb1, rgb2, depth1=None, depth2=None, K=None, init=None, solver=None) -> dict:
        """rgb: (B,3,H,W) in [0,1]; depth: metres (B,1,H,W): sparse LiDAR, or IP-Basic dense;
        K, init, solver: see `flow_pose`."""
        out: dict = {}
        if self.cfg.uses_depth:
            dense = self.complete(torch.cat([rgb1, rgb2]), torch.cat([depth1, depth2]))
            out["dense1"], out["dense2"] = dense.chunk(2)
        else:
            dense = None
        feats, depths, greys = self.encode(torch.cat([rgb1, rgb2]), dense)
        first = lambda xs: [None if x is None else x.chunk(2)[0] for x in xs]  # noqa: E731
        second = lambda xs: [None if x is None else x.chunk(2)[1] for x in xs]  # noqa: E731
        lidar = self.lidar_levels(inverse_depth(depth1, self.cfg.min_depth)) if self.cfg.gn_lidar else None
        out.update(self.flow_pose(first(feats), second(feats), first(depths), first(greys), second(greys), K, init,
                                  lidar, solver, second(depths)))
        return out
