"""The pose loss of eq. 11-12, with learnable balance terms s_t, s_q (Kendall-style).

l_l = |t_gt - t_l|_1 exp(-s_t) + s_t + |q_gt/|q_gt| - q_l/|q_l||_2^2 exp(-s_q) + s_q, and
l = sum_l alpha_l l_l over the flow levels. The confidence-weighted final pose (eq. 10) is
scored the same way with weight `alpha_final`: without that term the weights w_l would get no
gradient at all.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn


@dataclass
class LossConfig:
    alphas: tuple[float, ...] = (0.2, 0.4, 0.8, 1.6)  # coarse to fine; the last len(levels) are used
    alpha_final: float = 1.6
    # "data": s_t, s_q start at log of the no-motion predictor's error on the training pairs, so
    # both terms of eq. 11 start at weight ~1/error. Frame-to-frame rotations are ~0.5 deg, so
    # |dq|^2 ~ 2e-5 and PoseNet's s_q = -3 (for absolute poses) leaves rotation ~1000x underweighted.
    balance_init: str = "data"  # data | config (use s_t_init, s_q_init)
    s_t_init: float = 0.0
    s_q_init: float = -3.0
    completion_weight: float = 0.2  # L1 (m) on depth GT where the data has it (synthetic depth_2)
    flow_weight: float = 0.5  # EPE (cells of each level) against the rigid flow of GT depth + GT pose
    # binary cross-entropy of the point head's 'moves on its own' logits against the motion masks
    motion_weight: float = 1.0
    # the target also counts as moving the pixels of surfaces that stay put where a moving
    # vehicle's shadow changes the shading by the next frame (`d3lvo synth` writes shadow_2/ with
    # traffic): they move in the image with the vehicle and pull the pose the same way. Off by
    # default, so that the bundled model's training stages (scripts/train_default.sh) repeat exactly
    moving_shadows: bool = False
    # the point head: eq. 11 on the solver's own poses, backpropagated through the Gauss-Newton
    # steps into the confidence, so that it learns which points help the pose, not only which move;
    # 0: the confidence learns from the motion masks alone (and training runs no solver)
    solver_pose_weight: float = 0.0

    def __post_init__(self) -> None:
        if self.balance_init not in ("data", "config"):
            raise ValueError(f"balance_init must be data or config, not {self.balance_init!r}")


def _canonical(q: torch.Tensor) -> torch.Tensor:
    q = q / q.norm(dim=-1, keepdim=True).clamp(min=1e-8)
    return torch.where(q[..., :1] < 0, -q, q)


class PoseLoss(nn.Module):
    def __init__(self, cfg: LossConfig = LossConfig()):
        super().__init__()
        self.cfg = cfg
        self.s_t = nn.Parameter(torch.tensor(float(cfg.s_t_init)))
        self.s_q = nn.Parameter(torch.tensor(float(cfg.s_q_init)))

    @torch.no_grad()
    def init_balance(self, t_err: float, q_err: float) -> None:
        """Start s_t, s_q at log of the given typical errors (see LossConfig.balance_init)."""
        self.s_t.fill_(float(torch.log(torch.tensor(max(t_err, 1e-8)))))
        self.s_q.fill_(float(torch.log(torch.tensor(max(q_err, 1e-12)))))

    def level(self, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        """Eq. 11 for (B,7) predictions against (B,7) ground truth, batch mean."""
        t_err = (gt[:, :3] - pred[:, :3]).abs().sum(-1)
        q_err = (_canonical(gt[:, 3:]) - _canonical(pred[:, 3:])).pow(2).sum(-1)
        return (t_err * torch.exp(-self.s_t) + self.s_t + q_err * torch.exp(-self.s_q) + self.s_q).mean()

    def forward(self, levels: torch.Tensor, final: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """levels: (B,L,7) coarse to fine; final: (B,7); gt: (B,7)."""
        n = levels.shape[1]
        alphas = self.cfg.alphas[-n:]
        parts = {f"level{i}": self.level(levels[:, i], gt) for i in range(n)}
        total = sum(a * parts[f"level{i}"] for i, a in enumerate(alphas)) + self.cfg.alpha_final * self.level(final, gt)
        return total, {k: float(v.detach()) for k, v in parts.items()}
