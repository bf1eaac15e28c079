"""P of eq. 8-9 as the point solver under a learned confidence: what the network adds to a classical tracker.

At the finest flow level, a small conv net reads where the starting motion (constant velocity at
run time) fails to explain frame t: the disagreement between the learned flow and that motion's
rigid flow, frame t's depth against the depth the motion predicts, and frame t's features warped
rigidly and by the flow against frame t-1's, beside the inverse depth (with pt_conf_inputs="all"
also the flow estimator's state and frame t-1's features, from which it learns appearance and
place priors that flag static road as moving); it predicts per cell the logit that the cell lies
on something that moves on its own. It is trained directly against the synthetic drives' motion
masks (binary cross-entropy, `models.train`). Each LiDAR point of frame t-1 takes the confidence
1 - p(moving) of the cell it projects to, and `point_solver.solve` runs the classical direct
tracker with those weights: on a static scene the confidence stays near 1 and the pose is the
classical one; a truck that keeps the ego speed gets weight near 0 instead of pulling the pose
along.

Why not regress the pose (the paper's MLP) or weight cells of a half-size view: measured in
docs/evaluation.md, both lost to the classical tracker, whose only weakness is that it cannot
tell what moves.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from d3lvo_deploy.points import CLASSICAL_INPUT, CLASSICAL_START_INPUT, SCAN_DEPTH_INPUT

from . import gauss_newton as gn
from .config import D3LVOConfig
from .flow import warp
from .layers import conv
from .point_solver import (NO_EVIDENCE, SolverSettings, consensus_gain, image_pyramids, lidar_depth_error, project,
                           pyramid_input_names, rotations_differ, solve)


def solver_settings(cfg: D3LVOConfig) -> SolverSettings:
    """The point solver's settings in a model config."""
    return SolverSettings(tuple(cfg.pt_iters), cfg.pt_stop, cfg.pt_damping, cfg.pt_scale_every, cfg.pt_refine,
                          cfg.pt_affine, cfg.pt_fine_restart, cfg.pt_restart_depth, cfg.pt_median_stride,
                          cfg.pt_scan_gate)


class MovingLogits(nn.Module):
    """Per-cell logit of 'moves on its own'; starts at p = 0.05 everywhere (nearly classical).
    Dilated convs: a vehicle's interior has no texture, its evidence is at its edges, up to ~15
    cells away."""

    def __init__(self, cin: int, width: int = 32):
        super().__init__()
        self.net = nn.Sequential(conv(cin, width, k=1), conv(width, width, dilation=1), conv(width, width, dilation=2),
                                 conv(width, width, dilation=4), nn.Conv2d(width, 1, 3, padding=1))
        nn.init.normal_(self.net[-1].weight, std=1e-3)
        nn.init.constant_(self.net[-1].bias, -3.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


def _cell_grid(h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    """(1, h*w, 2) cell coordinates (u, v), row-major as `gn.backproject` lays out its points."""
    v = torch.arange(h, dtype=like.dtype, device=like.device).view(h, 1).expand(h, w)
    u = torch.arange(w, dtype=like.dtype, device=like.device).view(1, w).expand(h, w)
    return torch.stack([u, v], -1).reshape(1, h * w, 2)


def interleave(a: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(B,...) twice -> (2B,...): rows 2i and 2i + 1 are a[i] and c[i], two solves of pair i that
    `point_solver.solve` runs on one copy of its images."""
    return torch.stack([a, c], 1).flatten(0, 1)


def distrusted_share(weight: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B,) the share of frame t-1's points (mask above 0) the network distrusts: weight under 0.5,
    where `consensus_gain`'s trusted points begin."""
    valid = (mask > 0).to(weight.dtype)
    return (valid * (weight < 0.5).to(weight.dtype)).sum(1) / valid.sum(1).clamp(min=1.0)


class PointPose(nn.Module):
    def __init__(self, cfg: D3LVOConfig):
        super().__init__()
        self.cfg = cfg
        self.level = cfg.flow_levels[-1]
        # flow - rigid flow, inverse depth and three residuals of the rigid motion: depth, features
        # warped rigidly, features warped by the flow; with "all", the hidden state and frame t-1's
        # features too
        looks = cfg.flow_hidden[1] + cfg.feature_widths[self.level] if cfg.pt_conf_inputs == "all" else 0
        self.moving = MovingLogits(2 + 1 + 3 + looks)
        self.settings = solver_settings(cfg)

    def moving_logits(self, hidden: torch.Tensor, flow: torch.Tensor, feat1: torch.Tensor, feat2: torch.Tensor,
                      invdepth1: torch.Tensor, invdepth2: torch.Tensor, K: torch.Tensor,
                      init: torch.Tensor) -> torch.Tensor:
        """(B,1,h,w) at the finest flow level, from where the starting motion (constant velocity at
        run time) fails to explain frame t: the flow, the depth and the features. Inputs are
        detached: flow, features and depth learn from their own losses."""
        b, _, h, w = invdepth1.shape
        scale = float(2 ** (self.level + 1))
        X, _ = gn.backproject(invdepth1, K, scale, self.cfg.min_depth)
        Xt = gn.apply(gn.invert(init), X)
        uv, _ = gn.project(Xt, K, scale)
        grid = _cell_grid(h, w, X)
        rigid = (uv - grid).transpose(1, 2).reshape(b, 2, h, w)
        expected = self.cfg.min_depth / Xt[..., 2].clamp(min=0.1)
        seen = gn.sample(invdepth2, uv)[:, 0]
        depth_res = ((seen - expected) / expected.clamp(min=1e-3)).clamp(-1.0, 1.0).reshape(b, 1, h, w)
        rigid_res = (gn.sample(feat2, uv).reshape(feat1.shape) - feat1).abs().mean(1, keepdim=True)
        flow_res = (warp(feat2, flow) - feat1).abs().mean(1, keepdim=True)
        if self.cfg.pt_conf_inputs == "all":
            x = torch.cat([hidden, flow - rigid, invdepth1, feat1, depth_res, rigid_res, flow_res], 1)
        else:
            x = torch.cat([flow - rigid, invdepth1, depth_res, rigid_res, flow_res], 1)
        return self.moving(x.detach())

    def point_confidence(self, confidence: torch.Tensor, points: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
        """(B,N): each point takes the confidence of the cell it projects to in the network view
        (bilinear; points outside the view, the crop's margins, take the nearest border cell)."""
        uv, _, _ = project(points, K)
        s = float(2 ** (self.level + 1))  # cell i sits on view pixel s*i
        h, w = confidence.shape[-2:]
        grid = torch.stack([2.0 * uv[..., 0] / s / (w - 1) - 1.0, 2.0 * uv[..., 1] / s / (h - 1) - 1.0], -1)
        return F.grid_sample(confidence, grid.unsqueeze(1), mode="bilinear", padding_mode="border",
                             align_corners=True)[:, 0, 0]

    def point_weights(self, confidence: torch.Tensor, solver: dict, K: torch.Tensor) -> torch.Tensor:
        """(B,N) the solver's weight of each of frame t-1's points: the point list's mask times its
        confidence (`point_confidence`), gated, capped and raised to the power the config sets."""
        conf = self.point_confidence(confidence, solver["points1"], K)
        if self.cfg.pt_gate > 0:
            conf = (conf > self.cfg.pt_gate).to(conf.dtype)
        if self.cfg.pt_conf_full < 1:
            conf = torch.clamp(conf / self.cfg.pt_conf_full, max=1.0)
        return solver["point_mask1"] * conf ** self.cfg.pt_conf_power

    def distrusted_against(self, hidden: torch.Tensor, flow: torch.Tensor, feat1: torch.Tensor, feat2: torch.Tensor,
                           invdepth1: torch.Tensor, invdepth2: torch.Tensor, K: torch.Tensor, motion: torch.Tensor,
                           solver: dict) -> torch.Tensor:
        """(B,) `distrusted_share` of the confidence read with `motion` as the motion its evidence is
        measured against (rather than the pair's start)."""
        logits = self.moving_logits(hidden, flow, feat1, feat2, invdepth1, invdepth2, K, motion)
        return distrusted_share(self.point_weights(torch.sigmoid(-logits), solver, K), solver["point_mask1"])

    def pyramids(self, solver: dict) -> tuple[list, list]:
        """Both frames' image pyramids for `solve`: the exported graph's inputs where `solver` has
        them, else made from its grey images (training)."""
        grey1, stack2 = pyramid_input_names(len(self.settings.iterations))
        if grey1[0] in solver:
            return [solver[n] for n in grey1], [solver[n] for n in stack2]
        return image_pyramids(solver["image1"], solver["image2"], len(self.settings.iterations))

    def classical_solve(self, solver: dict, init: torch.Tensor) -> torch.Tensor:
        """(B,4,4) the classical mode's pose (every point of the list at weight 1) from `init`: the
        solve `forward` batches beside the weighted one, alone. It reads no network output, so the
        runtime runs it on a core of its own while completion and encoder run (the rows of a batch
        cost time, docs/performance.md), then passes it to the flow+pose graph as `CLASSICAL_INPUT`."""
        grey1, stack2 = self.pyramids(solver)
        mask = solver["point_mask1"]
        return solve(grey1, stack2, solver["points1"], mask, solver["image_intrinsics"], init, self.settings,
                     mask=mask, depth2=solver.get(SCAN_DEPTH_INPUT))[-1]

    @staticmethod
    def scan_errors(weighted: torch.Tensor, classical: torch.Tensor, solver: dict, weight: torch.Tensor) -> torch.Tensor:
        """(B,2): `lidar_depth_error` of the weighted and the classical pose (B,4,4) against frame t's
        scan (`SCAN_DEPTH_INPUT`), over the points the network trusts (weight at least 0.5, as
        `consensus_gain`'s), both in one batch on one copy of the scan."""
        two = lambda x: interleave(x, x)  # noqa: E731
        points, K = solver["points1"], solver["image_intrinsics"]
        trusted = (weight >= 0.5).to(points.dtype)
        return lidar_depth_error(interleave(weighted, classical), two(points), two(trusted), solver[SCAN_DEPTH_INPUT],
                                 two(K)).reshape(-1, 2)

    def forward(self, hidden: torch.Tensor, flow: torch.Tensor, feat1: torch.Tensor, feat2: torch.Tensor,
                invdepth1: torch.Tensor, invdepth2: torch.Tensor, K: torch.Tensor, init: torch.Tensor,
                solver: dict | None) -> dict:
        """Tensors at the finest flow level; K (B,4) of the network view; init (B,4,4) the start.
        `solver`: both frames' image pyramids (`pyramid_input_names`; the exported graph's inputs)
        or image1, image2 (B,1,H,W) grey at the camera's resolution (training), points1 (B,N,3),
        point_mask1 (B,N), image_intrinsics (B,4), with `pt_restart_depth` or `pt_scan_gate` scan_depth2 (B,1,H,W) frame
        t's LiDAR depth at the camera's resolution; without it only the logits."""
        logits = self.moving_logits(hidden, flow, feat1, feat2, invdepth1, invdepth2, K, init)
        confidence = torch.sigmoid(-logits)
        out = {"moving_logits": logits, "confidence": [confidence]}
        if solver is None:
            return out
        weight = self.point_weights(confidence, solver, K)
        grey1, stack2 = self.pyramids(solver)
        points, mask, K_image = solver["points1"], solver["point_mask1"], solver["image_intrinsics"]
        if self.cfg.pt_select > 0:
            # the classical solve too, and its pose unless the weighted one explains the points the
            # network trusts better by more than pt_select (`consensus_gain`). Given as
            # `CLASSICAL_INPUT` (the runtime solved it beside completion and encoder,
            # `classical_solve`), else in one batch with the weighted one: batch rows 2i and 2i + 1
            # are pair i's two solves, which share its images (no copy)
            if CLASSICAL_INPUT in solver:
                levels = solve(grey1, stack2, points, weight, K_image, init, self.settings, mask=mask,
                               depth2=solver.get(SCAN_DEPTH_INPUT))
                classical = solver[CLASSICAL_INPUT]
            else:
                two = lambda x: interleave(x, x)  # noqa: E731
                # `pt_classical_chain`: the classical solve from its own previous pose where given
                starts = interleave(init, solver.get(CLASSICAL_START_INPUT, init))
                both = solve(grey1, stack2, two(points), interleave(weight, mask), two(K_image), starts,
                             self.settings, mask=two(mask), depth2=solver.get(SCAN_DEPTH_INPUT))
                levels, classical = [L[0::2] for L in both], both[-1][1::2]
            gain = consensus_gain(levels[-1], classical, grey1[0], stack2[0], points, weight, K_image)
            # the next pair starts from the weighted pose, whichever is kept: started from a
            # classical pose that tracked a vehicle, the weighted solve would track it too
            out["start_next"] = levels[-1]
            keep = gain > self.cfg.pt_select
            if self.cfg.pt_select_rotation > 0:
                keep = keep & rotations_differ(levels[-1], classical, self.cfg.pt_select_rotation)
            if self.cfg.pt_select_share < 1:
                keep = keep & (distrusted_share(weight, mask) <= self.cfg.pt_select_share)
            if self.cfg.pt_select_unexplained > 0:
                # the evidence read again against the classical pose: what it leaves unexplained
                # (a start far off makes a static scene look as if it moved; the classical pose
                # does not, unless it followed something that moves)
                unexplained = self.distrusted_against(hidden, flow, feat1, feat2, invdepth1, invdepth2, K, classical,
                                                      solver)
                keep = keep & (unexplained > self.cfg.pt_select_unexplained)
            if (self.cfg.pt_select_scan > 0 or self.cfg.pt_select_scan_pass > 0) and SCAN_DEPTH_INPUT in solver:
                # (training's samples carry no scan: there the photometric test alone decides)
                fits = self.scan_errors(levels[-1], classical, solver, weight)  # (B,2): weighted, classical
                # both poses put trusted points on frame t's returns (else 1e9): the scan judges
                evidence = (fits < NO_EVIDENCE).all(1)
                if self.cfg.pt_select_scan > 0:
                    keep = keep & ((fits[:, 0] <= self.cfg.pt_select_scan * fits[:, 1]) | ~evidence)
                if self.cfg.pt_select_scan_pass > 0:
                    keep = keep | ((fits[:, 0] < self.cfg.pt_select_scan_pass * fits[:, 1]) & evidence)
            levels = [*levels[:-1], torch.where(keep[:, None, None], levels[-1], classical)]
            out["consensus_gain"], out["classical"] = gain, classical  # for choosing the thresholds offline
            out["select_kept"] = keep.to(gain.dtype)  # 1 where the weighted pose is kept (`pt_select_hold`)
        else:
            levels = solve(grey1, stack2, points, weight, K_image, init, self.settings, mask=mask,
                           depth2=solver.get(SCAN_DEPTH_INPUT))
        out["point_weights"] = weight
        out["level_matrices"] = levels
        return out
