"""Image-guided depth completion in the spirit of PENet (Hu et al. 2021; paper Sec. III-A).

A colour-dominant branch (RGB + sparse depth) and a depth-dominant branch (sparse depth + the
first branch's estimate, fed the first branch's decoder features) each predict depth and a
confidence; the two are fused by softmax over confidences, then a full-resolution residual
refinement corrects the fused map. Both branches work from h/2 down to h/8 to fit a CPU budget.
Everything is in inverse depth (min_depth / d) through a sigmoid, so the output is positive and
bounded: depth in [min_depth, max_depth] metres.
"""

from __future__ import annotations

import torch
from torch import nn

from .layers import ResBlock, conv, inverse_depth, resize_like


class _Branch(nn.Module):
    """Encoder-decoder h/2 -> h/8 -> h/2 with skips; returns (inverse-depth logit, confidence, features)."""

    def __init__(self, cin: int, widths: tuple[int, ...], guide: tuple[int, ...] | None = None):
        super().__init__()
        w = widths
        self.down = nn.ModuleList([nn.Sequential(conv(cin, w[0], stride=2), ResBlock(w[0]))])
        for a, b in zip(w[:-1], w[1:]):
            self.down.append(nn.Sequential(conv(a, b, stride=2), ResBlock(b)))
        self.up = nn.ModuleList([conv(b, a) for a, b in zip(w[:-1], w[1:])][::-1])
        self.guide = guide
        self.head = nn.Conv2d(w[0], 2, 3, padding=1)

    def forward(self, x: torch.Tensor, guide_feats: list[torch.Tensor] | None = None):
        skips = []
        for i, d in enumerate(self.down):
            x = d(x)
            if guide_feats is not None and i < len(guide_feats):
                x = x + guide_feats[i]
            skips.append(x)
        feats = [skips[-1]]
        for up, skip in zip(self.up, skips[-2::-1]):
            x = up(resize_like(x, skip)) + skip
            feats.append(x)
        out = self.head(x)
        return out[:, :1], out[:, 1:], feats[::-1]  # features fine to coarse


class DepthCompletion(nn.Module):
    def __init__(self, widths: tuple[int, ...], min_depth: float, max_depth: float):
        super().__init__()
        self.min_depth, self.max_depth = min_depth, max_depth
        self.colour = _Branch(3 + 2, widths)
        self.depth = _Branch(3, widths)
        self.refine = nn.Sequential(conv(3 + 3, 8), conv(8, 8), nn.Conv2d(8, 1, 3, padding=1))

    def forward(self, rgb: torch.Tensor, sparse: torch.Tensor) -> torch.Tensor:
        """rgb: normalised (B,3,H,W); sparse: metres (B,1,H,W), 0 = no return. Returns metres."""
        inv_s = inverse_depth(sparse, self.min_depth)
        valid = (sparse > 0).to(rgb.dtype)
        cd_logit, cd_conf, cd_feats = self.colour(torch.cat([rgb, inv_s, valid], 1))
        cd_inv = torch.sigmoid(cd_logit)
        dd_in = torch.cat([inv_s, valid, resize_like(cd_inv, inv_s)], 1)
        dd_logit, dd_conf, _ = self.depth(dd_in, guide_feats=cd_feats)
        w = torch.softmax(torch.cat([cd_conf, dd_conf], 1), dim=1)
        fused_logit = w[:, :1] * cd_logit + w[:, 1:] * dd_logit
        fused_logit = resize_like(fused_logit, rgb)
        residual = self.refine(torch.cat([rgb, inv_s, valid, torch.sigmoid(fused_logit)], 1))
        inv = torch.sigmoid(fused_logit + residual)
        return (self.min_depth / inv.clamp(min=self.min_depth / self.max_depth)).clamp(max=self.max_depth)
