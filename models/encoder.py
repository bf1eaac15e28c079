"""The 4-level RGB-D feature pyramid with attention (paper Sec. III-B, Fig. 2).

The 4-channel RGB-D input is split into an RGB stream and a depth stream, because eq. 1 (CA)
acts on RGB features and eq. 2 (SA) on depth features. Each level halves the resolution with a
strided conv and a residual block (h/2, h/4, h/8, h/16). The two streams are fused per level by
a 1x1 conv, plus cross attention (eq. 3) at `xa_levels`. Alongside the features, the encoder
returns frame depth at each level (as min_depth/d) for G(D) and the pose head, and, for the
Gauss-Newton pose head, a grey image per level; it runs once per frame, so the runtime can cache
it for the next pair.

Level l (stride s = 2^(l+1)) cell (i, j) is centred on input pixel (s*i, s*j): a stride-2 conv with
padding 1 centres output i on input 2i. Depth per level is therefore the input depth at those
pixels (strided slicing, not pooling: an average of inverse depths across an object boundary is a
surface that does not exist, and back-projecting it puts points in mid-air), and the grey image
is smoothed by a box of s+1 pixels centred there.
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from .attention import ChannelAttention, CrossAttention, SpatialAttention
from .config import D3LVOConfig
from .layers import ResBlock, conv


class PyramidEncoder(nn.Module):
    def __init__(self, cfg: D3LVOConfig):
        super().__init__()
        self.cfg = cfg
        self.rgb = nn.ModuleList()
        self.ca = nn.ModuleList()
        self.dep = nn.ModuleList()
        self.sa = nn.ModuleList()
        self.fuse = nn.ModuleList()
        self.xa = nn.ModuleDict()
        cin_r, cin_d = 3, 1
        for lvl in range(4):
            cr, cd, cf = cfg.rgb_widths[lvl], cfg.depth_widths[lvl], cfg.feature_widths[lvl]
            # only levels the flow uses get fused features: an unused head would be a dead branch
            used = lvl in cfg.flow_levels
            self.rgb.append(nn.Sequential(conv(cin_r, cr, stride=2), ResBlock(cr)))
            self.ca.append(ChannelAttention(cr, cfg.ca_reduction))
            if cfg.uses_depth:
                self.dep.append(nn.Sequential(conv(cin_d, cd, stride=2), ResBlock(cd)))
                self.sa.append(SpatialAttention())
                if lvl in cfg.xa_levels and used:
                    self.xa[str(lvl)] = CrossAttention(cr, cd, cfg.xa_dim, cf)
            self.fuse.append(conv(cr + (cd if cfg.uses_depth else 0), cf, k=1) if used else nn.Identity())
            cin_r, cin_d = cr, cd

    def forward(self, rgb: torch.Tensor, inv_depth: torch.Tensor | None):
        """rgb normalised (B,3,H,W); inv_depth (B,1,H,W) or None in rgb mode.

        Returns fine-to-coarse lists indexed by level: features (None at levels the flow does not
        use) and depth (empty in rgb mode).
        """
        feats: list[torch.Tensor | None] = []
        depths: list[torch.Tensor] = []
        xr, xd = rgb, inv_depth
        for lvl in range(4):
            xr = self.ca[lvl](self.rgb[lvl](xr))
            used = lvl in self.cfg.flow_levels
            if self.cfg.uses_depth:
                xd = self.sa[lvl](self.dep[lvl](xd))
                inv_depth = inv_depth[..., ::2, ::2]
                depths.append(inv_depth)
                f = self.fuse[lvl](torch.cat([xr, xd], 1)) if used else None
                if used and str(lvl) in self.xa:
                    f = f + self.xa[str(lvl)](xr, xd)
            else:
                f = self.fuse[lvl](xr) if used else None
            feats.append(f)
        return feats, depths

    def grey_pyramid(self, rgb: torch.Tensor) -> list[torch.Tensor | None]:
        """Per level: the mean of the normalised RGB channels, box-smoothed and sampled at the
        level's cell centres (None at levels without a Gauss-Newton step)."""
        grey = rgb.mean(1, keepdim=True)
        out: list[torch.Tensor | None] = []
        for lvl in range(4):
            s = 2 ** (lvl + 1)
            used = lvl in self.cfg.gn_levels
            out.append(F.avg_pool2d(grey, s + 1, stride=s, padding=s // 2, count_include_pad=False) if used else None)
        return out
