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


def bilinear_inside(x: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """x (B,C,h,w) at GridSample coordinates grid (B,2,N) -> (B,C,N) for positions inside the
    image ([-1, 1]); outside, finite values the caller masks. For few channels: GatherElements
    on x as it is (no copy of x, which the Gauss-Newton steps sample fifteen times)."""
    b, c = x.shape[:2]
    last = _size(x, grid.dtype) - 1.0
    p = torch.minimum(((grid + 1.0) * 0.5 * last).clamp(min=0.0), last)
    p0 = torch.minimum(torch.floor(p), last - 1.0)
    first = torch.cat([torch.ones_like(last[:, :1]), last[:, :1] + 1.0], 2) @ p0  # (B,1,N)
    corners = first + torch.cat([torch.zeros_like(last[:, :1]), torch.ones_like(last[:, :1]), last[:, :1] + 1.0,
                                 last[:, :1] + 2.0], 1)
    v = torch.gather(x.flatten(2), 2, corners.long().reshape(b, 1, -1).expand(b, c, -1)).reshape(b, c, 4, -1)
    return (v * _corner_weights(p - p0).unsqueeze(1)).sum(2)
