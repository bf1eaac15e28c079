"""Small building blocks shared by the components."""

from __future__ import annotations

import functools

import torch
from torch import nn
import torch.nn.functional as F


def conv(cin: int, cout: int, k: int = 3, stride: int = 1, dilation: int = 1, act: bool = True,
         bn: bool = False) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, k, stride, padding=dilation * (k // 2), dilation=dilation, bias=not bn)]
    if bn:
        layers.append(nn.BatchNorm2d(cout))
    if act:
        layers.append(nn.LeakyReLU(0.1, inplace=True))
    return nn.Sequential(*layers)


class ResBlock(nn.Module):
    def __init__(self, ch: int):
        super().__init__()
        self.c1 = nn.Conv2d(ch, ch, 3, padding=1)
        self.c2 = nn.Conv2d(ch, ch, 3, padding=1)
        self.act = nn.LeakyReLU(0.1, inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(x + self.c2(self.act(self.c1(x))))


def resize_like(x: torch.Tensor, ref: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    size = ref.shape[-2:]
    if x.shape[-2:] == size:
        return x
    if mode == "bilinear":
        h, w = int(x.shape[-2]), int(x.shape[-1])  # static in an export, as every size of the network
        factor = int(size[0]) // h
        if x.shape[1] == 1 and factor > 1 and (int(size[0]), int(size[1])) == (h * factor, w * factor):
            return upsample_bilinear(x, factor)
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    return F.interpolate(x, size=size, mode=mode)


def _phase_weights(factor: int) -> torch.Tensor:
    """(factor^2, 1, 3, 3): output phase (ky, kx) of a bilinear upsampling by `factor` (half-pixel
    centres) as weights on the 3x3 input neighbourhood: source offset o = (k + 0.5) / factor - 0.5
    splits between the centre and the neighbour on o's side. Built per call (a few numbers, a
    constant in a traced graph): a cached tensor makes torch.compile warn on every compile."""
    taps = []
    for k in range(factor):
        o = (k + 0.5) / factor - 0.5
        taps.append([-o, 1 + o, 0.0] if o < 0 else [0.0, 1 - o, o])
    t = torch.tensor(taps, dtype=torch.float64)
    return (t[:, None, :, None] * t[None, :, None, :]).reshape(factor * factor, 1, 3, 3)


def upsample_bilinear(x: torch.Tensor, factor: int) -> torch.Tensor:
    """F.interpolate(x, scale_factor=factor, mode="bilinear", align_corners=False) of a 1-channel
    (B,1,h,w) map, as a 3x3 convolution to the factor^2 output phases (edge-padded: the border
    clamp) and DepthToSpace. OpenVINO's Interpolate took 5.3 ms to bring completion's h/4 map to
    1216x352 (docs/performance.md); a convolution and a pixel shuffle are kernels it runs fast."""
    w = _phase_weights(factor).to(dtype=x.dtype, device=x.device)
    return F.pixel_shuffle(F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), w), factor)


def adaptive_avg_pool(x: torch.Tensor, out_hw: tuple[int, int]) -> torch.Tensor:
    """AdaptiveAvgPool2d written as fixed slices + means (torch's bin rule).

    Shapes are static at export, so this traces to plain Slice/ReduceMean and exports for any
    input size, where ONNX's pooling needs sizes divisible by the output.
    """
    h, w = int(x.shape[-2]), int(x.shape[-1])
    oh, ow = out_hw
    rows = []
    for i in range(oh):
        h0, h1 = (i * h) // oh, -((-(i + 1) * h) // oh)
        cols = []
        for j in range(ow):
            w0, w1 = (j * w) // ow, -((-(j + 1) * w) // ow)
            cols.append(x[:, :, h0:h1, w0:w1].mean(dim=(2, 3)))
        rows.append(torch.stack(cols, -1))
    return torch.stack(rows, -2)


def inverse_depth(depth: torch.Tensor, min_depth: float) -> torch.Tensor:
    """min_depth / depth in (0, 1]; holes (depth <= 0) become 0, i.e. 'infinitely far / unknown'."""
    valid = depth > 0
    return torch.where(valid, min_depth / depth.clamp(min=min_depth), torch.zeros_like(depth))


def _to_fp32(x):
    if isinstance(x, torch.Tensor):
        return x.float() if x.is_floating_point() else x
    if isinstance(x, dict):
        return {k: _to_fp32(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_to_fp32(v) for v in x)
    return x


def full_precision(fn):
    """Run `fn` in float32 even under mixed-precision autocast: the pose solvers' normal equations
    (6x6 sums over thousands of points, steps of a millimetre) lose the pose in bf16 or fp16."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        kinds = [d for d in ("cuda", "cpu") if torch.is_autocast_enabled(d)]
        if not kinds:
            return fn(*args, **kwargs)
        with torch.autocast(kinds[0], enabled=False):
            return fn(*_to_fp32(args), **_to_fp32(kwargs))

    return wrapper

