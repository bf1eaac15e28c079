"""Depth-aware optical flow, coarse to fine (paper Sec. III-D, eq. 6-7).

At each level: warp F2 by the upsampled coarser flow, build the cost volume, process it with
a 1x1 and a 3x3 conv + ReLU, and let F (1x1 convs 128-64-2 with BN + LeakyReLU) predict the flow
(coarsest level, eq. 6: u = F * G(D)) or its residual (eq. 7: u = up(u') + G(D) * du).
G(D) expands depth to 32 channels, then a 1x1 conv and 2*sigmoid: a per-pixel factor in (0, 2),
1 at initialisation, that scales flow magnitude by scene depth. A context net with dilated
convolutions refines the finest flow from the estimator's features and the flow itself.
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from . import sampling
from .config import D3LVOConfig
from .correlation import cost_volume
from .layers import conv


def warp(x: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Sample x at p + flow(p) (bilinear, zeros outside): brings frame-2 features onto frame 1."""
    b, c, h, w = x.shape
    ys = torch.arange(h, dtype=x.dtype, device=x.device).view(1, h, 1).expand(b, h, w)
    xs = torch.arange(w, dtype=x.dtype, device=x.device).view(1, 1, w).expand(b, h, w)
    if sampling.gathering():
        uv = torch.stack([xs, ys], 1) + flow
        return sampling.bilinear(x, uv.reshape(b, 2, h * w)).reshape(b, c, h, w)
    gx = 2.0 * (xs + flow[:, 0]) / max(w - 1, 1) - 1.0
    gy = 2.0 * (ys + flow[:, 1]) / max(h - 1, 1) - 1.0
    return F.grid_sample(x, torch.stack([gx, gy], -1), mode="bilinear", padding_mode="zeros", align_corners=True)


def upsample_flow(flow: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear upsampling; flow vectors scale with the resolution ratio of each axis."""
    h, w = flow.shape[-2:]
    up = F.interpolate(flow, size=size, mode="bilinear", align_corners=False)
    return torch.cat([up[:, :1] * (size[1] / w), up[:, 1:] * (size[0] / h)], 1)


class DepthGate(nn.Module):
    """G(D): depth -> 32 channels -> 1x1 conv -> 2*sigmoid."""

    def __init__(self, width: int = 32):
        super().__init__()
        self.expand = conv(1, width)
        self.out = nn.Conv2d(width, 1, 1)
        nn.init.normal_(self.out.weight, std=1e-3)  # G ~ 1 at start, yet gradients reach `expand`
        nn.init.zeros_(self.out.bias)

    def forward(self, inv_depth: torch.Tensor) -> torch.Tensor:
        return 2.0 * torch.sigmoid(self.out(self.expand(inv_depth)))


class FlowLevel(nn.Module):
    def __init__(self, cfg: D3LVOConfig, feat_ch: int, coarsest: bool):
        super().__init__()
        self.cfg, self.coarsest = cfg, coarsest
        n_disp = (2 * cfg.search_range + 1) ** 2
        self.cost = nn.Sequential(
            # 1x1 first: mixing the 81 matching scores per pixel needs no neighbourhood, and a 3x3
            # over 81 channels was the single largest conv of the flow stage at h/4
            nn.Conv2d(n_disp, cfg.cost_width, 1), nn.ReLU(inplace=True),
            nn.Conv2d(cfg.cost_width, cfg.cost_width, 3, padding=1), nn.ReLU(inplace=True),
        )
        h1, h2 = cfg.flow_hidden
        cin = cfg.cost_width + feat_ch + (0 if coarsest else 2)
        self.hidden = nn.Sequential(conv(cin, h1, k=1, bn=True), conv(h1, h2, k=1, bn=True))
        self.head = nn.Conv2d(h2, 2, 1)
        self.gate = DepthGate(cfg.depth_gate_width) if cfg.uses_depth else None

    def forward(self, f1, f2, flow_up, inv_depth):
        f2w = f2 if flow_up is None else warp(f2, flow_up)
        motion = self.cost(cost_volume(f1, f2w, self.cfg.search_range, self.cfg.correlation))
        x = torch.cat([motion, f1] + ([] if flow_up is None else [flow_up]), 1)
        hidden = self.hidden(x)
        du = self.head(hidden)
        g = self.gate(inv_depth) if self.gate is not None else 1.0
        flow = du * g if flow_up is None else flow_up + g * du
        return flow, hidden


class ContextNet(nn.Module):
    """Dilated convs (1, 2, 4, 8, 1) over [estimator features, flow] -> a flow correction."""

    def __init__(self, cin: int, width: int = 32):
        super().__init__()
        self.net = nn.Sequential(
            conv(cin, width, dilation=1), conv(width, width, dilation=2), conv(width, width, dilation=4),
            conv(width, width, dilation=8), nn.Conv2d(width, 2, 3, padding=1),
        )

    def forward(self, hidden: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
        return flow + self.net(torch.cat([hidden, flow], 1))
