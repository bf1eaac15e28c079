"""Image-guided depth completion in the spirit of PENet (Hu et al. 2021; paper Sec. III-A).

A colour-dominant branch (RGB + sparse depth) and a depth-dominant branch (sparse depth + the
first branch's estimate, fed the first branch's features) each predict depth and a confidence;
the two are fused by softmax over confidences, then a residual refinement corrects the fused map.
To fit a 10 Hz budget on a CPU, the branches encode h/2 -> h/8 and decode back to h/4, where
fusion and refinement happen; only the final map is resized to the input resolution. The encoder
consumes depth from h/2 down, and the flow and pose stages from h/4 down, so finer detail would
cost time nothing downstream uses. Everything is in inverse depth (min_depth / d) through a
sigmoid, so the output is positive and bounded: depth in [min_depth, max_depth] metres.
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from .layers import ResBlock, conv, inverse_depth, resize_like


class _Branch(nn.Module):
    """Encoder h/2 -> h/8 (one conv at h/2, conv + residual block below), decoder to h/4 with a skip.

    Returns the inverse-depth logit and confidence at h/4 and the features at h/2, h/4, h/8.
    """

    def __init__(self, cin: int, widths: tuple[int, int, int], first_stride: int = 2):
        super().__init__()
        w0, w1, w2 = widths
        self.down = nn.ModuleList([
            conv(cin, w0, stride=first_stride),
            nn.Sequential(conv(w0, w1, stride=2), ResBlock(w1)),
            nn.Sequential(conv(w1, w2, stride=2), ResBlock(w2)),
        ])
        self.up = conv(w2, w1)
        self.head = nn.Conv2d(w1, 2, 3, padding=1)

    def forward(self, x: torch.Tensor, guide: list[torch.Tensor] | None = None):
        skips = []
        for i, d in enumerate(self.down):
            x = d(x)
            if guide is not None:
                x = x + guide[i]
            skips.append(x)
        x = self.up(resize_like(x, skips[1])) + skips[1]
        out = self.head(x)
        return out[:, :1], out[:, 1:], [skips[0], x, skips[2]]


class DepthCompletion(nn.Module):
    def __init__(self, widths: tuple[int, int, int], min_depth: float, max_depth: float):
        super().__init__()
        self.min_depth, self.max_depth = min_depth, max_depth
        self.colour = _Branch(3 + 2, widths)
        self.depth = _Branch(3, widths, first_stride=1)  # its input is already at h/2
        self.refine = nn.Sequential(conv(3 + 3, 16), conv(16, 16), nn.Conv2d(16, 1, 3, padding=1))

    def forward(self, rgb: torch.Tensor, sparse: torch.Tensor) -> torch.Tensor:
        """rgb: normalised (B,3,H,W); sparse: metres (B,1,H,W), 0 = no return. Returns metres."""
        inv = self.forward_inverse(rgb, inverse_depth(sparse, self.min_depth))
        return (self.min_depth / inv).clamp(max=self.max_depth)

    def forward_inverse(self, rgb: torch.Tensor, inv_s: torch.Tensor) -> torch.Tensor:
        """The same in inverse depth (min_depth / d, 0 = no return), what the encoder consumes:
        the deployed graphs take and return this form, so no full-resolution conversion to metres
        and back runs between the stages. Output in [min_depth / max_depth, 1]."""
        valid = (inv_s > 0).to(rgb.dtype)
        cd_logit, cd_conf, cd_feats = self.colour(torch.cat([rgb, inv_s, valid], 1))
        # max-pooling inverse depth keeps the nearest LiDAR return of each cell
        half_inv, half_valid = F.max_pool2d(inv_s, 2), F.max_pool2d(valid, 2)
        dd_in = torch.cat([half_inv, half_valid, resize_like(torch.sigmoid(cd_logit), half_inv)], 1)
        dd_logit, dd_conf, _ = self.depth(dd_in, guide=cd_feats)
        w_cd = torch.sigmoid(cd_conf - dd_conf)  # = softmax over the two confidences, one op cheaper
        fused = dd_logit + w_cd * (cd_logit - dd_logit)  # h/4
        quarter = [F.avg_pool2d(rgb, 4), F.max_pool2d(inv_s, 4), F.max_pool2d(valid, 4)]
        residual = self.refine(torch.cat(quarter + [torch.sigmoid(fused)], 1))
        inv = torch.sigmoid(resize_like(fused + residual, rgb)).clamp(min=self.min_depth / self.max_depth)
        # LiDAR returns are kept as measured (the completion fills the holes between them): the
        # Gauss-Newton pose head back-projects these pixels, and a 1 cm return beats any prediction
        return torch.where(inv_s > 0, inv_s, inv)
