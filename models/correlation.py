"""The cost volume of eq. 4-5 with standard tensor ops only (no custom CUDA/C++ op), so it exports.

C(x, d) = sum_c F1~(x) F2~(x + d) over the (2S+1)^2 displacements d, with F~ = F / ||F||_2 per
pixel (eq. 5). Three formulations give the same numbers (up to float summation order); which is
fastest in onnxruntime is measured by `python -m export.correlation_bench`:
- slices: one multiply-and-sum per displacement. Cheap in torch (slices are views), but in
  onnxruntime each Slice copies, so 81 x (copy, multiply, reduce) passes over memory.
- stacked: the 81 shifted windows in one tensor, one multiply and reduce (81x the memory).
- tiled (default): rows are cut into tiles of T pixels; per vertical offset dy, a batched GEMM
  (T x C) @ (C x T+2S) dots every pixel of a tile with the window it can reach, and one Gather
  keeps the 2S+1 horizontal offsets of each pixel. ~2.7x redundant multiply-adds, but done by
  GEMM kernels instead of 243 memory-bound ops.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

TILE = 16  # pixels per row tile; 8 and 32 were measured slower in onnxruntime at 1216x352


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


def correlation_tiled(f1: torch.Tensor, f2: torch.Tensor, search: int, tile: int = TILE) -> torch.Tensor:
    """Per row tile and dy: GEMM of the tile's pixels with its reachable window, then the band."""
    c, h, w = (int(s) for s in f1.shape[1:])  # python ints: the export freezes them as constants
    b = -1  # the batch stays free (export with --dynamic-batch)
    n, t = 2 * search + 1, max(tile, 2 * search)  # a tile's window borrows 2S columns of the next tile
    nt = -(-w // t)
    wt = nt * t
    span = t + 2 * search  # window columns one tile can reach
    a = F.pad(f1, (0, wt - w)).reshape(b, c, h, nt, t).permute(0, 2, 3, 4, 1)  # (b, h, nt, t, c)
    f2p = F.pad(f2, (search, search + wt - w + t, search, search))  # (b, c, h+2S, wt+t+2S)
    head = f2p[..., :wt].reshape(b, c, h + 2 * search, nt, t)
    tail = f2p[..., t : wt + t].reshape(b, c, h + 2 * search, nt, t)[..., : 2 * search]
    win = torch.cat([head, tail], -1).permute(0, 2, 3, 1, 4)  # (b, h+2S, nt, c, span)
    # pixel i of a tile meets window columns i .. i+2S: flat indices into the (t, span) product
    i = torch.arange(t).view(t, 1)
    band = (i * span + i + torch.arange(n).view(1, n)).reshape(-1)
    rows = []
    for dy in range(n):
        prod = a @ win[:, dy : dy + h]  # (b, h, nt, t, span)
        rows.append(prod.reshape(b, h, nt, t * span)[..., band].reshape(b, h, wt, n)[:, :, :w])
    out = torch.stack(rows, 1)  # (b, dy, h, w, dx)
    return out.permute(0, 1, 4, 2, 3).reshape(b, n * n, h, w)


CORRELATIONS = {"slices": correlation_slices, "stacked": correlation_stacked, "tiled": correlation_tiled}


def cost_volume(f1: torch.Tensor, f2: torch.Tensor, search: int = 4, impl: str = "tiled") -> torch.Tensor:
    return CORRELATIONS[impl](l2_normalise(f1), l2_normalise(f2), search)
