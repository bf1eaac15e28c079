"""Which standard-op cost volume is faster in onnxruntime? (`python -m export.correlation_bench`)

Exports the normalise + correlation block alone, per formulation, at the pyramid shapes of a
given input size, and times it in onnxruntime. The README quotes this script's output.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from models.config import D3LVOConfig
from models.correlation import CORRELATIONS, cost_volume


class _Block(torch.nn.Module):
    def __init__(self, impl: str):
        super().__init__()
        self.impl = impl

    def forward(self, f1, f2):
        return cost_volume(f1, f2, 4, self.impl)


def time_formulation(impl: str, c: int, h: int, w: int, threads: int, runs: int) -> float:
    f = torch.randn(1, c, h, w)
    with tempfile.TemporaryDirectory() as d, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        path = Path(d) / "corr.onnx"
        torch.onnx.export(_Block(impl), (f, f), str(path), input_names=["f1", "f2"], output_names=["c"],
                          opset_version=17, dynamo=False)
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        feeds = {"f1": f.numpy(), "f2": np.roll(f.numpy(), 2, axis=3)}
        sess.run(None, feeds)
        times = []
        for _ in range(runs):
            t0 = time.perf_counter()
            sess.run(None, feeds)
            times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1000)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--height", type=int, default=352)
    ap.add_argument("--width", type=int, default=1216)
    ap.add_argument("--channels", type=int, nargs=3, default=D3LVOConfig().feature_widths[1:],
                    help="feature widths at h/4, h/8, h/16 (default: the default config's)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=10)
    a = ap.parse_args()
    print(f"cost volume (L2-normalise + 81 displacements) in onnxruntime, {a.threads} threads, median of {a.runs}")
    for impl in CORRELATIONS:
        total = 0.0
        parts = []
        for lvl, c in zip((1, 2, 3), a.channels):
            s = 2 ** (lvl + 1)
            ms = time_formulation(impl, c, a.height // s, a.width // s, a.threads, a.runs)
            total += ms
            parts.append(f"h/{s} {ms:6.1f} ms")
        print(f"  {impl:8s} " + "  ".join(parts) + f"  total {total:6.1f} ms")


if __name__ == "__main__":
    main()
