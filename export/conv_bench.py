"""Are onnxruntime's convolutions faster than torch eager's? Every conv of the network, alone, in both.
(`python -m export.conv_bench`)

Runs the three stages once in torch to record each Conv2d's shape (input size, channels, kernel,
stride), then times every distinct shape as a single layer in torch eager and in onnxruntime
(same threads, the runtime's session options). It separates the kernels from the graph: what
onnxruntime gains over torch on a whole stage beyond this table comes from fusion, layouts kept
between layers and memory planning, not from faster convolution kernels. A single-layer ORT
session also pays the layout reorder of its input and output, which inside a whole graph happens
only at boundaries, so its column is an upper bound. The README quotes this script's output.
"""

from __future__ import annotations

import argparse
import io
import time
import warnings
from collections import Counter
from dataclasses import dataclass

import numpy as np
import onnxruntime as ort
import torch
from torch import nn

from models.config import D3LVOConfig
from models.d3lvo import D3LVO
from models.layers import inverse_depth


@dataclass(frozen=True)
class ConvShape:
    cin: int
    cout: int
    k: int
    stride: int
    dilation: int
    groups: int
    height: int
    width: int

    @property
    def gmac(self) -> float:
        oh, ow = -(-self.height // self.stride), -(-self.width // self.stride)
        return self.cin // self.groups * self.cout * self.k * self.k * oh * ow / 1e9

    def label(self) -> str:
        return f"{self.cin:>3}->{self.cout:<3} {self.k}x{self.k}/{self.stride} at {self.width}x{self.height}"


def conv_layers(cfg: D3LVOConfig) -> Counter:
    """Each Conv2d call of one frame pair's stages (complete, encode, flow_pose), by shape."""
    torch.manual_seed(0)
    model = D3LVO(cfg).eval()
    seen: Counter = Counter()

    def hook(mod: nn.Conv2d, inputs, _out) -> None:
        x = inputs[0]
        seen[ConvShape(mod.in_channels, mod.out_channels, mod.kernel_size[0], mod.stride[0], mod.dilation[0],
                       mod.groups, int(x.shape[-2]), int(x.shape[-1]))] += 1

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv2d)]
    rgb = torch.rand(1, 3, cfg.height, cfg.width)
    sparse = torch.rand(1, 1, cfg.height, cfg.width) * 50
    with torch.no_grad():
        dense = model.complete(rgb, sparse) if cfg.uses_depth else None
        feats, depths, greys = model.encode(rgb, dense)
        model.flow_pose(feats, feats, depths, greys, greys, lidar1=model.lidar_levels(inverse_depth(sparse, cfg.min_depth)))
    for h in handles:
        h.remove()
    return seen


def _median_ms(fn, runs: int) -> float:
    fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1000)


def time_shape(s: ConvShape, threads: int, runs: int) -> tuple[float, float]:
    """(torch eager ms, onnxruntime ms) for one layer of this shape."""
    torch.set_num_threads(threads)
    conv = nn.Conv2d(s.cin, s.cout, s.k, s.stride, s.dilation * (s.k // 2), s.dilation, s.groups).eval()
    x = torch.randn(1, s.cin, s.height, s.width)
    with torch.no_grad():
        t_torch = _median_ms(lambda: conv(x), runs)
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(conv, (x,), buf, input_names=["x"], output_names=["y"], opset_version=17, dynamo=False)
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.add_session_config_entry("session.intra_op.allow_spinning", "1")  # as the runtime runs (SessionConfig)
    so.add_session_config_entry("session.force_spinning_stop", "1")
    sess = ort.InferenceSession(buf.getvalue(), so, providers=["CPUExecutionProvider"])
    feeds = {"x": x.numpy()}
    return t_torch, _median_ms(lambda: sess.run(None, feeds), runs)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--height", type=int, default=352)
    ap.add_argument("--width", type=int, default=1216)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=10)
    a = ap.parse_args(argv)
    layers = conv_layers(D3LVOConfig(height=a.height, width=a.width))
    print(f"every conv of the default network at {a.width}x{a.height}, alone, {a.threads} threads, median of {a.runs}")
    print(f"  {'layer':34s} {'calls':>5s} {'GMAC':>6s} {'torch ms':>9s} {'ORT ms':>8s} {'speed-up':>8s}")
    tot_t = tot_o = 0.0
    for s, n in sorted(layers.items(), key=lambda kv: (-kv[0].height * kv[0].width, kv[0].cin, kv[0].cout)):
        t, o = time_shape(s, a.threads, a.runs)
        tot_t += n * t
        tot_o += n * o
        print(f"  {s.label():34s} {n:5d} {n * s.gmac:6.3f} {n * t:9.2f} {n * o:8.2f} {t / o:7.2f}x")
    print(f"  {'all convs':34s} {sum(layers.values()):5d} {sum(n * s.gmac for s, n in layers.items()):6.3f} "
          f"{tot_t:9.2f} {tot_o:8.2f} {tot_t / tot_o:7.2f}x")


if __name__ == "__main__":
    main()
