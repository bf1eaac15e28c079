"""Hierarchical, depth-aware pose refinement (paper Sec. III-E, eq. 8-10).

Each flow level l has a pose net P that sees the level's flow features, the flow, depth D_l and
the running pose T_l, and predicts a residual: T_{l+1} = T_l + dT_l (eq. 8-9). A pose is a
7-vector (translation in metres, quaternion w, x, y, z); the sum is taken on that vector, as
the paper writes it, with the quaternion renormalised after each step (and its delta scaled to
the size of frame-to-frame rotations). P: two strided convs to a fixed
grid (adaptive pooling, so any input size works), then the MLP 256-128-64 with LeakyReLU and
dropout. Each level also emits a confidence logit; softmax over levels gives the weights w_l of
T_final = sum_l w_l T_l (eq. 10).
"""

from __future__ import annotations

import torch
from torch import nn

from .config import D3LVOConfig
from .layers import adaptive_avg_pool, conv

IDENTITY = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
# frame-to-frame rotations are ~0.5 deg, i.e. ~4e-3 in quaternion units, while translations are
# ~1 m: the quaternion part of dT is scaled so that the head's unit outputs mean ~1 deg
ROT_SCALE = 0.01


class PoseLevel(nn.Module):
    def __init__(self, cfg: D3LVOConfig, cin: int):
        super().__init__()
        self.pool = cfg.pose_pool
        pw = cfg.pose_width
        self.enc = nn.Sequential(conv(cin, pw, stride=2), conv(pw, pw, stride=2))
        layers: list[nn.Module] = []
        width = pw * cfg.pose_pool[0] * cfg.pose_pool[1] + 7
        for hidden in cfg.pose_hidden:
            layers += [nn.Linear(width, hidden), nn.LeakyReLU(0.1, inplace=True), nn.Dropout(cfg.dropout)]
            width = hidden
        self.mlp = nn.Sequential(*layers)
        self.delta = nn.Linear(width, 7)
        self.conf = nn.Linear(width, 1)
        nn.init.normal_(self.delta.weight, std=1e-3)  # start near identity, but keep gradients alive
        nn.init.zeros_(self.delta.bias)

    def forward(self, x: torch.Tensor, pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z = adaptive_avg_pool(self.enc(x), self.pool).flatten(1)
        h = self.mlp(torch.cat([z, pose], 1))
        d = self.delta(h)
        d = torch.cat([d[:, :3], d[:, 3:] * ROT_SCALE], 1)
        # renormalised after each step: left free, training inflated |q| to ~3, which shrinks the
        # normalised rotation (and its gradient) 3x and froze the predicted rotation
        return normalise_pose(pose + d), self.conf(h)


def normalise_pose(p: torch.Tensor) -> torch.Tensor:
    q = p[..., 3:]
    return torch.cat([p[..., :3], q / q.norm(dim=-1, keepdim=True).clamp(min=1e-8)], -1)


def pose_to_matrix(p: torch.Tensor) -> torch.Tensor:
    """(..., 7) translation + quaternion (w, x, y, z; any norm) -> (..., 4, 4)."""
    t = p[..., :3]
    q = p[..., 3:] / p[..., 3:].norm(dim=-1, keepdim=True).clamp(min=1e-8)
    w, x, y, z = q.unbind(-1)
    R = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(p.shape[:-1] + (3, 3))
    top = torch.cat([R, t.unsqueeze(-1)], -1)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=p.dtype, device=p.device).expand(p.shape[:-1] + (1, 4))
    return torch.cat([top, bottom], -2)
