"""What one block of the point solver's Gauss-Newton steps costs on OpenVINO, and which parts of it.

    .venv/bin/python scripts/solver_block_cost.py [SEQ] [--rounds 4] [--runs 300]

Runs the bundled model in PyTorch on SEQ's first three frames (default: the 20 real KITTI frames
of ../shared/data) and keeps the inputs of its largest finest-level block (the full-resolution
image). That block is exported alone as the flow+pose graph's Loop body is (`export/solver_loop.py`'s
`_Block`, OpenVINO's layout) six ways, each opened with the runtime's OpenVINO session
(`d3lvo_deploy.backends.OpenVinoSession`, 2 threads, inputs read in place) and timed on those
inputs, taking turns:

- as shipped;
- without the exposure match (`pt_affine` off: frame t's grey against frame t-1's as it is);
- with the 6x6 solve replaced by a stand-in of one op (g divided by H's diagonal): not a
  solver, only what the block costs without one;
- with the Huber threshold's median (a TopK partial sort of every point's residual) replaced by
  the masked mean: what the median costs;
- on the weighted solves' rows alone (the coarse-to-fine solve and the restart; the classical
  mode's two rows left to the `classical` stage), and on one row: what a batch's rows cost.

Figures: docs/performance.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path

import onnx
import torch

import models.point_solver as ps
from d3lvo_deploy.bundled import bundled_model_dir, find_real_frames
from d3lvo_deploy.cpu import cpu_info
from models.checkpoint import build_model, load_checkpoint
from models.predict import predict_sequence


def finest_block_inputs(seq: Path) -> list:
    """gn_steps' arguments of the block with the largest image, from the bundled model in torch."""
    model = build_model(load_checkpoint(bundled_model_dir() / "default.pt"))
    kept: dict[str, list] = {}
    steps = ps.gn_steps

    def record(*a, **k):
        if "args" not in kept or a[4].shape[-1] > kept["args"][4].shape[-1]:
            kept["args"] = [x.clone() if torch.is_tensor(x) else x for x in a]
        return steps(*a, **k)

    ps.gn_steps = record
    try:
        with torch.no_grad():
            predict_sequence(model, seq, end=3)
    finally:
        ps.gn_steps = steps
    return kept["args"]


# gn_steps' arguments with a row per solve: the pose, the stop flag, the points, frame t-1's grey,
# the grid intrinsics, the focal lengths, the three weights and the sampling offsets
PER_ROW = (0, 1, 2, 3, 5, 6, 7, 8, 9, 13)


def rows_of(args: list, rows: list[int]) -> list:
    """The block's arguments for some of its solves. Rows per pair: the weighted and the classical
    coarse-to-fine solve, then their restarts (`point_solver._finest_with_restart`)."""
    return [a[rows].contiguous() if j in PER_ROW else a for j, a in enumerate(args)]


def masked_mean(a: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """A stand-in for `masked_median` without its partial sort (not a robust scale)."""
    return (a * mask).sum(-1, keepdim=True) / mask.sum(-1, keepdim=True).clamp(min=1.0)


def compiled_block(args: list, settings: ps.SolverSettings, solve, path: Path, median=None):
    """The block exported as the Loop's body with `solve` for the 6x6 system (and `median` for
    the Huber threshold's, if given), opened as the runtime opens a stage; returns (session,
    feeds, graph ops)."""
    from d3lvo_deploy.backends import OpenVinoSession, SessionConfig
    from export.solver_loop import _Block

    n_in = 14  # gn_steps' tensors; then the steps, the settings and the sampling layout
    Xh, stack = args[2], args[4]
    layout = (Xh.shape[0] // stack.shape[0], 3, Xh.shape[-1])  # as `block_graph` passes it
    shipped = ps.scaled_solve, ps.masked_median
    ps.scaled_solve, ps.masked_median = solve, median or ps.masked_median
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(_Block(replace(settings, scale_every=args[n_in]), layout), tuple(args[:n_in]),
                              str(path), input_names=[f"in{j}" for j in range(n_in)],
                              dynamic_axes={"in4": {2: "h", 3: "w"}}, opset_version=17, dynamo=False)
    finally:
        ps.scaled_solve, ps.masked_median = shipped
    ops = sum(n.op_type != "Constant" for n in onnx.load(str(path)).graph.node)
    session = OpenVinoSession(path, SessionConfig(threads=2, backend="openvino"), "flowpose")
    names = {name for name, _ in session.inputs}
    feeds = {f"in{j}": args[j].contiguous().numpy() for j in range(n_in) if f"in{j}" in names}
    return session, feeds, ops


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("seq", nargs="?", type=Path, default=find_real_frames())
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--runs", type=int, default=300)
    a = p.parse_args(argv)
    if a.seq is None:
        sys.exit("error: give SEQ (a KITTI odometry sequence): ../shared/data has no real frames here")
    if not (a.seq / "image_2").is_dir():
        sys.exit(f"error: {a.seq}: no image_2/ folder (a KITTI odometry sequence is needed)")
    torch.set_num_threads(2)
    os.environ.setdefault("D3LVO_CACHE", tempfile.mkdtemp())  # compile these graphs, keep none
    args = finest_block_inputs(a.seq)
    settings = args[15]
    print(f"CPU: {cpu_info().model}; block of {args[14]} steps, {args[2].shape[0]} solves of "
          f"{args[2].shape[-1]} points, image {tuple(args[4].shape)}")
    with tempfile.TemporaryDirectory() as tmp:
        variants = {
            "as shipped": compiled_block(args, settings, ps.scaled_solve, Path(tmp) / "a.onnx"),
            "without the exposure match": compiled_block(args, replace(settings, affine=False), ps.scaled_solve,
                                                         Path(tmp) / "b.onnx"),
            "solve replaced by one op": compiled_block(args, settings, lambda Hb, d: Hb[:, :, 6:] / d,
                                                       Path(tmp) / "c.onnx"),
            "median replaced by a mean": compiled_block(args, settings, ps.scaled_solve, Path(tmp) / "d.onnx",
                                                        median=masked_mean),
            "the weighted rows alone": compiled_block(rows_of(args, [0, 2]), settings, ps.scaled_solve,
                                                      Path(tmp) / "e.onnx"),
            "one row": compiled_block(rows_of(args, [0]), settings, ps.scaled_solve, Path(tmp) / "f.onnx"),
        }
        times: dict[str, list[float]] = {k: [] for k in variants}
        for _ in range(a.rounds):
            for k, (session, feeds, _) in variants.items():
                for _ in range(5):
                    session.run(feeds)
                t = time.perf_counter()
                for _ in range(a.runs):
                    session.run(feeds)
                times[k].append((time.perf_counter() - t) / a.runs * 1000)
    first = next(iter(variants))
    for k, (_, _, ops) in variants.items():
        print(f"{k:28s} {ops:4d} graph ops, ms per block: " + " / ".join(f"{t:.2f}" for t in times[k]))
    for k in list(variants)[1:]:  # each round's pair taken a moment apart: the VM's drift cancels
        saved = statistics.median(a - b for a, b in zip(times[first], times[k]))
        print(f"{k}: {saved:.2f} ms less per block than {first} (median of the rounds' differences, "
              f"{100 * saved / statistics.median(times[first]):.0f} %)")


if __name__ == "__main__":
    main()
