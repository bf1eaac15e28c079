"""Attention of the feature pyramid (paper Sec. III-B, eq. 1-3)."""

from __future__ import annotations

import torch
from torch import nn


class ChannelAttention(nn.Module):
    """Eq. 1: CA(x) = sigmoid(w2 relu(w1 [GAP(x), GMP(x)])) * x, on the RGB stream.

    The shared two-layer MLP sees GAP and GMP side by side (2C inputs), as the equation writes
    the concatenation inside w1.
    """

    def __init__(self, ch: int, reduction: int = 4):
        super().__init__()
        hidden = max(ch // reduction, 4)
        self.w1 = nn.Linear(2 * ch, hidden)
        self.w2 = nn.Linear(hidden, ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = torch.cat([x.mean(dim=(2, 3)), x.amax(dim=(2, 3))], dim=1)
        gate = torch.sigmoid(self.w2(torch.relu(self.w1(pooled))))
        return x * gate[:, :, None, None]


class SpatialAttention(nn.Module):
    """Eq. 2: SA(x) = sigmoid(f3x3([max_c x, mean_c x])) * x, on the depth stream."""

    def __init__(self):
        super().__init__()
        self.f = nn.Conv2d(2, 1, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = torch.cat([x.amax(dim=1, keepdim=True), x.mean(dim=1, keepdim=True)], dim=1)
        return x * torch.sigmoid(self.f(pooled))


class CrossAttention(nn.Module):
    """Eq. 3: XA = softmax(q_r k_d^T / sqrt(d_k)) v_d + softmax(q_d k_r^T / sqrt(d_k)) v_r.

    RGB queries read depth and depth queries read RGB over all positions of the level. Memory
    and time grow with (H W)^2, so the default places it at h/16 only (1,672 tokens at 1216x352;
    h/8 would be 6,688 tokens and a 45M-entry attention matrix per direction on a CPU).
    """

    def __init__(self, rgb_ch: int, depth_ch: int, dim: int, out_ch: int):
        super().__init__()
        self.q_r, self.k_r, self.v_r = (nn.Conv2d(rgb_ch, dim, 1) for _ in range(3))
        self.q_d, self.k_d, self.v_d = (nn.Conv2d(depth_ch, dim, 1) for _ in range(3))
        self.out = nn.Conv2d(dim, out_ch, 1)
        self.scale = dim ** -0.5

    @staticmethod
    def _tokens(x: torch.Tensor) -> torch.Tensor:
        return x.flatten(2).transpose(1, 2)  # (B, HW, dim)

    def forward(self, xr: torch.Tensor, xd: torch.Tensor) -> torch.Tensor:
        b, _, h, w = xr.shape
        qr, kr, vr = (self._tokens(m(xr)) for m in (self.q_r, self.k_r, self.v_r))
        qd, kd, vd = (self._tokens(m(xd)) for m in (self.q_d, self.k_d, self.v_d))
        r_reads_d = torch.softmax(qr @ kd.transpose(1, 2) * self.scale, dim=-1) @ vd
        d_reads_r = torch.softmax(qd @ kr.transpose(1, 2) * self.scale, dim=-1) @ vr
        fused = (r_reads_d + d_reads_r).transpose(1, 2).reshape(b, -1, h, w)
        return self.out(fused)
