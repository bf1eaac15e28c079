"""What one block of Gauss-Newton steps costs per engine and layout (`python -m export.solver_bench`).

The flow+pose graph runs the point solver as Loops over blocks of `scale_every` steps
(`export/solver_loop.py`), for a batch of two (the weighted and the classical solve). This
exports one block alone, in both layouts the export writes (OpenVINO's: GridSample and
Gauss-Jordan elimination; onnxruntime's: GatherElements and Cramer's rule with one Det op), and
onnxruntime's with elimination in place of Cramer's rule (what the Det op saves), feeds
it a textured image and 2,048 points in view, and times it with the engines taking turns. It
prints the graph ops per block and the median and 10th-percentile time per block, and for
onnxruntime the costliest node kinds from its profiler (which adds a few microseconds to every
node) and OpenVINO's (its per-node counters). The bundled model's level runs up to five blocks.
`--median-stride N` exports the blocks with `pt_median_stride` N (the Huber threshold's median
over every N-th point: a partial sort of N times fewer values).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
import onnx
import onnxruntime as ort
import torch

from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.points import bilinear
from export.solver_loop import BODY_INPUTS, block_graph
from models import point_solver, sampling
from models.config import D3LVOConfig
from models.gauss_newton import grid_intrinsics
from models.point_solver import SolverSettings
from models.pose_points import solver_settings

# the runtime's precision: left to itself, OpenVINO runs bf16 on CPUs with AMX or AVX512-BF16
OV_F32 = {"INFERENCE_PRECISION_HINT": "f32"}
LAYOUTS = {"gather": "GatherElements + Cramer (Det)", "gather_gj": "GatherElements + Gauss-Jordan",
           "gridsample": "GridSample + Gauss-Jordan"}


def block_feeds(height: int, width: int, points: int, batch: int = 2, seed: int = 0) -> dict[str, np.ndarray]:
    """A block's inputs: one pair's smooth random texture and its derivatives (`with_gradients`,
    as the solver takes them) shared by `batch` solves, as the weighted and the classical solve
    share it; points 5-30 m ahead in view, 0.3 m of forward motion to recover."""
    rng = np.random.default_rng(seed)
    f = 0.58 * width
    grey = np.repeat(cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), 3)[None, None],
                     batch, 0)
    z = rng.uniform(5.0, 30.0, (batch, 1, points))
    u, v = rng.uniform(0, width - 1, (batch, 1, points)), rng.uniform(0, height - 1, (batch, 1, points))
    X = np.concatenate([(u - width / 2) * z / f, (v - height / 2) * z / f, z, np.ones_like(z)], 1).astype(np.float32)
    K = torch.tensor([[f, f, width / 2, height / 2]] * batch)
    P = np.tile(np.eye(3, 4, dtype=np.float32), (batch, 1, 1))
    P[:, 2, 3] = -0.3
    ones = np.ones((batch, 1, points), np.float32)
    ref = np.stack([bilinear(grey[b, 0], np.stack([u[b, 0], v[b, 0]], 1))[None] for b in range(batch)])
    stack = point_solver.with_gradients(torch.from_numpy(grey[:1]))
    G = grid_intrinsics(K, torch.tensor([width, height], dtype=torch.float32))
    feeds = dict(P=P, active=np.ones((batch, 1, 1), np.float32), Xh=X, ref=ref.astype(np.float32),
                 stack=stack.numpy(), G=G.numpy(), f=np.full((batch, 2, 1), f, np.float32), weight=ones, w_ok=ones,
                 median_mask=ones)
    feeds.update({k: t.numpy() for k, t in zip(BODY_INPUTS[-4:], sampling.inside_lattice(stack, torch.zeros(batch)))})
    return feeds


def bundled_settings(median_stride: int | None = None) -> SolverSettings:
    """The bundled model's solver settings (exposure match and block length included: they set
    what a step holds), with `median_stride` in place of its own where given."""
    cfg = D3LVOConfig.from_dict(json.loads((bundled_model_dir() / "manifest.json").read_text())["model_config"])
    s = solver_settings(cfg)
    return s if median_stride is None else replace(s, median_stride=median_stride)


def export_block(layout: str, points: int, path: Path, batch: int = 2, median_stride: int | None = None) -> int:
    """One block in a `LAYOUTS` layout with the bundled model's settings; returns its non-constant ops."""
    eliminate = mock.patch.object(point_solver, "cramer_solve", point_solver.scaled_solve)
    with sampling.gathered(layout != "gridsample"), warnings.catch_warnings(), \
            (eliminate if layout == "gather_gj" else contextlib.nullcontext()):
        warnings.simplefilter("ignore")
        g = block_graph(bundled_settings(median_stride), points, 17, False, batch, images=1)
    onnx.save(onnx.helper.make_model(g, opset_imports=[onnx.helper.make_opsetid("", 17)]), str(path))
    return sum(n.op_type != "Constant" for n in g.node)


def _runner(engine: str, path: Path, feeds: dict, threads: int):
    if engine == "onnxruntime":
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        s = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
        fd = {i.name: feeds[i.name] for i in s.get_inputs()}
        return lambda: s.run(None, fd)
    import openvino as ov

    c = ov.Core().compile_model(str(path), "CPU", {"INFERENCE_NUM_THREADS": threads, **OV_F32})
    r = c.create_infer_request()
    fd = {i.get_any_name(): feeds[i.get_any_name()] for i in c.inputs}
    return lambda: r.infer(fd, share_inputs=True)  # as the runtime: no copy of the image stack per call


def top_nodes(path: Path, feeds: dict, threads: int, runs: int = 100, top: int = 6) -> list[tuple[str, float]]:
    """onnxruntime's profiler: microseconds per block by node kind, the costliest first."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.enable_profiling = True
    so.profile_file_prefix = str(path.with_suffix(""))
    s = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    fd = {i.name: feeds[i.name] for i in s.get_inputs()}
    for _ in range(runs):
        s.run(None, fd)
    by: dict[str, float] = collections.defaultdict(float)
    for e in json.load(open(s.end_profiling())):
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            by[e["args"]["op_name"]] += e["dur"] / runs
    return sorted(by.items(), key=lambda kv: -kv[1])[:top]


def openvino_top_nodes(path: Path, feeds: dict, threads: int, runs: int = 100, top: int = 6) -> list[tuple[str, float]]:
    """OpenVINO's per-node counters: microseconds per block by executed node kind, the costliest first."""
    import openvino as ov

    c = ov.Core().compile_model(str(path), "CPU", {"INFERENCE_NUM_THREADS": threads, "PERF_COUNT": "YES", **OV_F32})
    r = c.create_infer_request()
    fd = {i.get_any_name(): feeds[i.get_any_name()] for i in c.inputs}
    by: dict[str, float] = collections.defaultdict(float)
    for _ in range(runs):
        r.infer(fd, share_inputs=True)
        for p in r.profiling_info:
            by[p.node_type] += p.real_time.total_seconds() * 1e6 / runs
    return sorted(by.items(), key=lambda kv: -kv[1])[:top]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--height", type=int, default=176)
    ap.add_argument("--width", type=int, default=608)
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=15, help="turns per engine and layout, 20 blocks each")
    ap.add_argument("--median-stride", type=int, default=None,
                    help="pt_median_stride of the exported blocks (default: the bundled model's)")
    a = ap.parse_args()
    feeds = block_feeds(a.height, a.width, a.points)
    cases = [("onnxruntime", "gather"), ("onnxruntime", "gather_gj"), ("onnxruntime", "gridsample")]
    try:
        import openvino  # noqa: F401

        cases.append(("openvino", "gridsample"))
    except ImportError:
        pass
    with tempfile.TemporaryDirectory() as d:
        paths = {k: Path(d) / f"block_{k}.onnx" for k in LAYOUTS}
        ops = {k: export_block(k, a.points, p, median_stride=a.median_stride) for k, p in paths.items()}
        runners = {c: _runner(c[0], paths[c[1]], feeds, a.threads) for c in cases}
        for run in runners.values():
            for _ in range(10):
                run()
        times: dict[tuple, list[float]] = {c: [] for c in cases}
        for _ in range(a.rounds):
            for c, run in runners.items():
                for _ in range(20):
                    t = time.perf_counter()
                    run()
                    times[c].append(time.perf_counter() - t)
        s = bundled_settings(a.median_stride)
        print(f"one block of {s.scale_every} Gauss-Newton steps (the bundled model's settings, exposure match "
              f"{'on' if s.affine else 'off'}), batch 2 x {a.points} points, {a.width}x{a.height} image, "
              f"{a.threads} threads, fp32, median over every {s.median_stride} point(s)")
        for (engine, layout), t in times.items():
            ms = np.array(t) * 1e3
            print(f"  {engine:12s} {LAYOUTS[layout]:30s} {ops[layout]:4d} ops  median {np.median(ms):.3f} ms  "
                  f"p10 {np.percentile(ms, 10):.3f} ms")
        for layout in ("gather", "gridsample"):
            kinds = ", ".join(f"{k} {v:.0f}" for k, v in top_nodes(paths[layout], feeds, a.threads))
            print(f"  onnxruntime profile, {layout} layout (us per block): {kinds}")
        if ("openvino", "gridsample") in runners:
            kinds = ", ".join(f"{k} {v:.0f}" for k, v in openvino_top_nodes(paths["gridsample"], feeds, a.threads))
            print(f"  openvino profile, gridsample layout (us per block): {kinds}")


if __name__ == "__main__":
    main()
