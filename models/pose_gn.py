"""Depth-aware geometric pose refinement: dT_l = P(F_l, D_l, T_l) as weighted Gauss-Newton (eq. 8-9).

At level l, frame t-1's cells are back-projected with the level's depth D_l (the LiDAR returns
where `gn_points="lidar"`, the default: completed depth between returns misleads the solver), moved by the
running estimate T_l and projected into frame t, where the residual is the difference of frame
t's features (sampled bilinearly) and frame t-1's: the grey image (a photometric term, as
DVL-SLAM's direct LiDAR-visual tracking) and `gn_features` learned channels (feature-metric, as
PixLoc). Each pixel is weighted by a confidence the network predicts from the flow estimator's
features and from the disagreement between the predicted flow and the rigid flow of T_l (moving
objects, occlusions and sky disagree), times a Huber weight. `gn_iters` damped steps are taken
per level, coarse to fine, T_{l+1} = exp(dT) T_l; levels finer than the flow (`gn_extra_levels`)
refine with the grey image and the upsampled confidence. Eq. 10's weights w_l are learned per level.

Why geometry instead of the paper's MLP regression: the MLP must learn projective geometry from
pooled features, which a CPU training budget did not achieve (it never predicted rotation); here
the geometry is exact and the network learns only what to trust.
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from . import gauss_newton as gn
from .config import D3LVOConfig
from .layers import conv, full_precision


class Confidence(nn.Module):
    """Per-pixel weight in (0, 2): 1 at initialisation, so training starts from plain GN."""

    def __init__(self, cin: int):
        super().__init__()
        self.net = nn.Sequential(conv(cin, 16, k=1), nn.Conv2d(16, 1, 3, padding=1))
        nn.init.normal_(self.net[-1].weight, std=1e-3)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 2.0 * torch.sigmoid(self.net(x))


class GaussNewtonPose(nn.Module):
    def __init__(self, cfg: D3LVOConfig):
        super().__init__()
        self.cfg = cfg
        self.features = nn.ModuleDict()
        self.confidence = nn.ModuleDict()
        for lvl in cfg.flow_levels:
            proj = nn.Conv2d(cfg.feature_widths[lvl], cfg.gn_features, 1)
            nn.init.normal_(proj.weight, std=1e-2)  # small: the photometric term leads at the start
            nn.init.zeros_(proj.bias)
            self.features[str(lvl)] = proj
            self.confidence[str(lvl)] = Confidence(cfg.flow_hidden[1] + 2)
        levels = len(cfg.gn_levels)
        # eq. 10's w_l: learned logits, starting in favour of the finest level
        self.level_logits = nn.Parameter(torch.linspace(-2.0, 2.0, levels))

    def rigid_flow(self, M: torch.Tensor, X: torch.Tensor, K: torch.Tensor, scale: float, shape) -> torch.Tensor:
        """Flow of frame t-1's cells under M, in level cells (B,2,h,w)."""
        h, w = shape
        uv, _ = gn.project(gn.apply(M, X), K, scale)
        v, u = torch.meshgrid(torch.arange(h, dtype=X.dtype, device=X.device),
                              torch.arange(w, dtype=X.dtype, device=X.device), indexing="ij")
        grid = torch.stack([u, v], -1).reshape(1, h * w, 2)
        return (uv - grid).transpose(1, 2).reshape(X.shape[0], 2, h, w)

    def align(self, M: torch.Tensor, f1: torch.Tensor, f2: torch.Tensor, conf: torch.Tensor, X: torch.Tensor,
              valid: torch.Tensor, K: torch.Tensor, scale: float) -> torch.Tensor:
        """`gn_iters` damped Gauss-Newton steps on sum_p conf(p) rho(|f2(pi(M X_p)) - f1(p)|^2)."""
        b, c, h, w = f2.shape
        gx, gy = gn.image_gradients(f2)
        return gn.feature_align(M, X, torch.cat([f2, gx, gy], 1), f1.reshape(b, c, h * w),
                                conf.reshape(b, h * w) * valid, K / scale, self.cfg.gn_iters, self.cfg.gn_huber,
                                self.cfg.gn_damping)

    @full_precision
    def forward(self, hidden: dict, flows: dict, feats1: dict, feats2: dict, grey1: dict, grey2: dict,
                depths1: dict, K: torch.Tensor, init: torch.Tensor):
        """Per-level dicts keyed by level; K (B,4) fx, fy, cx, cy at the input; init (B,4,4) the
        starting relative pose A (frame t in frame t-1: constant velocity at run time).
        Returns per-level poses (B,L,7), weights (B,L), the final pose (B,7) and per-level
        confidence maps."""
        M = gn.invert(init)
        poses, confs = [], {}
        conf = None
        for lvl in self.cfg.gn_levels:
            scale = float(2 ** (lvl + 1))
            # depth is trained by its own loss (completion L1), not through the solver: its gradient
            # through Gauss-Newton is large and noisy while the pose is still far off
            X, valid = gn.backproject(depths1[lvl].detach(), K, scale, self.cfg.min_depth)
            shape = depths1[lvl].shape[-2:]
            if lvl in self.cfg.flow_levels:
                # both inputs detached: the flow estimator learns flow from its own loss; the pose
                # loss, weighted by 1/error for frame-to-frame rotation, would otherwise drown it
                # (measured: with the features attached, flow EPE ended above zero flow's)
                disagreement = (flows[lvl] - self.rigid_flow(M, X, K, scale, shape)).detach()
                conf = self.confidence[str(lvl)](torch.cat([hidden[lvl].detach(), disagreement], 1))
                f1 = torch.cat([grey1[lvl], self.features[str(lvl)](feats1[lvl])], 1)
                f2 = torch.cat([grey2[lvl], self.features[str(lvl)](feats2[lvl])], 1)
            else:
                conf = F.interpolate(conf, size=shape, mode="bilinear", align_corners=True)
                f1, f2 = grey1[lvl], grey2[lvl]
            confs[lvl] = conf
            M = self.align(M, f1, f2, conf, X, valid, K, scale)
            poses.append(gn.matrix_to_pose(gn.invert(M)))
        levels = torch.stack(poses, 1)
        weights = torch.softmax(self.level_logits, 0).unsqueeze(0).expand(levels.shape[0], -1)
        return levels, weights, confs


def nominal_intrinsics(cfg: D3LVOConfig, batch: int = 1, dtype=torch.float32) -> torch.Tensor:
    """KITTI-like intrinsics at the network input (fx = fy = 0.59 w, centred): for code paths
    that time or count the network without a camera (stats, benchmarks)."""
    f = 0.59 * cfg.width
    return torch.tensor([[f, f, (cfg.width - 1) / 2, (cfg.height - 1) / 2]], dtype=dtype).expand(batch, 4)
