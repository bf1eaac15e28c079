"""The cost volume of eq. 4-5 with standard tensor ops only (no custom CUDA/C++ op), so it exports.

C(x, d) = sum_c F1~(x) F2~(x + d) over the (2S+1)^2 displacements d, with F~ = F / ||F||_2 per
pixel (eq. 5). Two formulations give identical numbers; which is faster in onnxruntime is
measured by the export issue, so both stay selectable.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def l2_normalise(f: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    return f / (f.pow(2).sum(1, keepdim=True) + eps * eps).sqrt()


def correlation_slices(f1: torch.Tensor, f2: torch.Tensor, search: int) -> torch.Tensor:
    """Pad F2 once, then one multiply-and-sum per displacement (row-major: dy outer, dx inner)."""
    h, w = f1.shape[-2:]
    f2p = F.pad(f2, (search, search, search, search))
    n = 2 * search + 1
    out = [(f1 * f2p[:, :, dy : dy + h, dx : dx + w]).sum(1) for dy in range(n) for dx in range(n)]
    return torch.stack(out, 1)


def correlation_stacked(f1: torch.Tensor, f2: torch.Tensor, search: int) -> torch.Tensor:
    """Stack the shifted windows into one (B,C,D,H,W) tensor, then a single multiply and reduce."""
    h, w = f1.shape[-2:]
    f2p = F.pad(f2, (search, search, search, search))
    n = 2 * search + 1
    windows = torch.stack([f2p[:, :, dy : dy + h, dx : dx + w] for dy in range(n) for dx in range(n)], 2)
    return (f1.unsqueeze(2) * windows).sum(1)


CORRELATIONS = {"slices": correlation_slices, "stacked": correlation_stacked}


def cost_volume(f1: torch.Tensor, f2: torch.Tensor, search: int = 4, impl: str = "slices") -> torch.Tensor:
    return CORRELATIONS[impl](l2_normalise(f1), l2_normalise(f2), search)
