"""Bilinear sampling (zeros outside, align_corners) as Gathers, in place of GridSample.

The model's bilinear samples are GridSample (`F.grid_sample`). onnxruntime's CPU GridSample
computes every sample of every channel on its own (a 32-channel warp of a 44x152 map takes
~2.5 ms there, ~1 ms on OpenVINO); the same sample as Gathers of whole pixel rows is faster on
onnxruntime and slower on OpenVINO, so export writes the flow+pose graph both ways: each
sampling site asks `gathering()` while `gathered()` is on (docs/performance.md).
"""

from __future__ import annotations

import contextlib

import torch
import torch.nn.functional as F

_GATHER = [False]


@contextlib.contextmanager
def gathered(on: bool = True):
    """Within: the model's sampling sites run `bilinear` / `bilinear_inside` instead of GridSample."""
    before, _GATHER[0] = _GATHER[0], on
    try:
        yield
    finally:
        _GATHER[0] = before


def gathering() -> bool:
    return _GATHER[0]


def _corner_weights(fr: torch.Tensor) -> torch.Tensor:
    """(B,2,N) fractional x, y -> (B,4,N) bilinear weights of the corners 00, 10, 01, 11."""
    a = torch.cat([1.0 - fr, fr], 1)  # 1-fx, 1-fy, fx, fy
    x = a.new_tensor([[1, 0, 0, 0], [0, 0, 1, 0], [1, 0, 0, 0], [0, 0, 1, 0]])
    y = a.new_tensor([[0, 1, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1], [0, 0, 0, 1]])
    return (x @ a) * (y @ a)


def image_size(img: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """(h, w) of a (B,C,h,w) tensor as a tensor: in an ONNX export read from the graph's tensor
    (a Shape op), so that the exported graph takes any image size; otherwise from the Python
    shape (torch.compile traces `_shape_as_tensor` to a torch.Size)."""
    if torch.onnx.is_in_onnx_export():
        return torch._shape_as_tensor(img)[2:].to(dtype)
    return torch.tensor(img.shape[2:], dtype=dtype, device=img.device)


def _size(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """(1,2,1) (w, h) of a (B,C,h,w) tensor, as `image_size`."""
    return image_size(x, dtype).flip(0).view(1, 2, 1)


def bilinear(x: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """x (B,C,h,w) at pixel positions uv (B,2,N) -> (B,C,N); zeros outside (a position between
    the border and one pixel beyond it blends with zero, as GridSample's zeros padding)."""
    b, c = x.shape[:2]
    # a zero border around x, so that a corner outside reads 0; pixel rows of C values to gather
    rows = F.pad(x, (1, 1, 1, 1)).permute(0, 2, 3, 1).reshape(-1, c)
    far = _size(x, uv.dtype)  # padded position of the zero column / row beyond the far border
    p = torch.minimum((uv + 1.0).clamp(min=0.0), far + 1.0)
    p0 = torch.minimum(torch.floor(p), far)
    wp = far[:, :1] + 2.0  # padded row length
    first = torch.cat([torch.ones_like(wp), wp], 2) @ p0  # (B,1,N) corner 00's row
    first = first + torch.arange(b, dtype=uv.dtype, device=uv.device).view(b, 1, 1) * (wp * (far[:, 1:] + 2.0))
    corners = first + torch.cat([torch.zeros_like(wp), torch.ones_like(wp), wp, wp + 1.0], 1)  # (B,4,N)
    v = rows[corners.long()]  # (B,4,N,C)
    return (v * _corner_weights(p - p0).unsqueeze(-1)).sum(1).transpose(1, 2)


def inside_lattice(x: torch.Tensor, solves: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """What `bilinear_inside` needs of x's size (G,C,h,w), computed once where x is sampled many
    times (the Gauss-Newton steps): half the last pixel position (1,2,1), the last cell's corner
    (1,2,1), the flat-index map (1, w) (1,1,2), and each sampling row's four corners' offsets in
    x flattened whole (S,C,4,1), int32. The S rows are those of `solves` (default: one per image),
    S = k G: rows i k .. i k + k - 1 read image i (several solves of one pair, one copy of its
    images)."""
    size = _size(x, x.dtype)  # (1,2,1): w, h
    w = size[:, :1]
    corners = torch.cat([torch.zeros_like(w), torch.ones_like(w), w, w + 1.0], 1)  # (1,4,1)
    channels = torch.arange(x.shape[1], dtype=x.dtype, device=x.device).view(1, -1, 1)  # no slice of x: a copy
    # int32: a narrower index than int64 is cheaper to build and to gather with; one image's
    # positions stay below 2^24, exact in float32, and the images' strides are added as integers
    offsets = (corners.unsqueeze(1) + (channels * (w * size[:, 1:])).unsqueeze(-1)).to(torch.int32)
    rows = x if solves is None else solves
    k = rows.shape[0] // x.shape[0]
    # row i's image i // k; (i + 1/2) / k lies at least 1/(2k) from an integer, so float rounding
    # cannot carry it across one (a floor division of integers exports as a dozen ops)
    image = torch.floor((torch.arange(rows.shape[0], dtype=x.dtype, device=x.device) + 0.5) / k).to(torch.int32)
    stride = (w * size[:, 1:] * float(x.shape[1])).to(torch.int32)  # (1,1,1): C h w
    offsets = offsets + (image.view(-1, 1, 1) * stride).unsqueeze(-1)  # (S,C,4,1)
    return (size - 1.0) * 0.5, size - 2.0, torch.cat([torch.ones_like(w), w], 2), offsets


def bilinear_inside(x: torch.Tensor, grid: torch.Tensor, lattice: tuple | None = None) -> torch.Tensor:
    """x (G,C,h,w) at GridSample coordinates grid (B,2,N) -> (B,C,N) for positions inside the
    image ([-1, 1]); outside, finite values the caller masks. B = G, or B = k G with `lattice`
    made for B rows (`inside_lattice(x, solves)`): grid rows i k .. i k + k - 1 sample image i.
    For few channels: one GatherElements on x as it is (no copy of x, which the Gauss-Newton
    steps sample fifteen times); `lattice` saves the ops that read x's size at every call."""
    half, last_cell, row_map, offsets = inside_lattice(x) if lattice is None else lattice
    p = (grid.clamp(-1.0, 1.0) + 1.0) * half
    p0 = torch.minimum(torch.floor(p), last_cell)
    index = (row_map @ p0).unsqueeze(1).to(torch.int32) + offsets  # (B,C,4,N) in x flattened whole
    v = torch.gather(x.reshape(1, -1), 1, index.reshape(1, -1)).view_as(index)
    return (v * _corner_weights(p - p0).unsqueeze(1)).sum(2)


def grid_sample_shared(x: torch.Tensor, grid: torch.Tensor, layout: tuple[int, int, int] | None = None
                       ) -> torch.Tensor:
    """F.grid_sample (zeros outside, align_corners) of x (G,C,h,w) at grid (B,2,N) -> (B,C,N),
    B = k G, grid rows i k .. i k + k - 1 on image i: `bilinear_inside`'s sharing with GridSample,
    image i's k grids side by side in one output row (reshapes, no copy of x). layout (k, C, N):
    Python ints where the caller knows them, so that an exported graph reshapes by constants
    (default from the shapes)."""
    k, c, n = (grid.shape[0] // x.shape[0], x.shape[1], grid.shape[-1]) if layout is None else layout
    g = grid.transpose(1, 2)  # (B,N,2)
    if k == 1:
        return F.grid_sample(x, g.unsqueeze(1), mode="bilinear", padding_mode="zeros", align_corners=True)[:, :, 0]
    out = F.grid_sample(x, g.reshape(-1, 1, k * n, 2), mode="bilinear", padding_mode="zeros",
                        align_corners=True)  # (G,C,1,kN)
    return out.reshape(-1, c, k, n).transpose(1, 2).reshape(-1, c, n)


def grid_sample_channels(x: torch.Tensor, grid: torch.Tensor, layout: tuple[int, int, int] | None = None
                         ) -> list[torch.Tensor]:
    """`grid_sample_shared` as one (B,1,N) tensor per channel of x: GridSample's output split by
    channel, which needs no transpose back to the points' rows (a (G,C,1,kN) channel is image i's
    k rows side by side, so it reshapes to (kG,1,N) as it is)."""
    k, c, n = (grid.shape[0] // x.shape[0], x.shape[1], grid.shape[-1]) if layout is None else layout
    out = F.grid_sample(x, grid.transpose(1, 2).reshape(-1, 1, k * n, 2), mode="bilinear", padding_mode="zeros",
                        align_corners=True)  # (G,C,1,kN)
    return [o.reshape(-1, 1, n) for o in out.split(1, 1)]
