"""Where onnxruntime's flow+pose stage loses time to OpenVINO's, part by part, on the same inputs.

    .venv/bin/python scripts/flowpose_parts.py [SEQ] [--onnx DIR] [--rounds 5]

Tracks SEQ (default: the 20 real KITTI frames of ../shared/data) with the model folder (default:
the bundled model) on onnxruntime (the `Odometry` API) and keeps the inputs its flow+pose stage
was given. Each engine's own flow+pose graph is then cut four ways and every
cut opened with the runtime's sessions (`d3lvo_deploy.backends`, 2 threads):

- as shipped;
- without the solver's steps: each Loop's trip count set to 0 (the poses are then wrong; what is
  timed is everything around the steps);
- the flow estimator and the confidence alone: the graph up to `flow_l1`, `confidence_l1` and
  `point_weights`;
- the flow estimator alone (its three levels and the context net): up to `flow_l1`.

All eight sessions take turns, call by call, on every recorded input for `--rounds` rounds, so
that they share the machine's drift; prints each one's median, and per engine what the solver's
steps, the point solver's setup around them and the confidence cost (the differences of the
cuts' medians) and the flow estimator's time. The model must have the point solver (its steps
are Loops).
Figures: docs/performance.md.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper
from onnx.utils import Extractor

from d3lvo_deploy.backends import SessionConfig, open_session
from d3lvo_deploy.bundled import bundled_model_dir, find_real_frames
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.manifest import for_engine, load_manifest
from d3lvo_deploy.odometry import Odometry
from d3lvo_deploy.sequence import KittiSequence

FLOW_OUTPUTS = ("flow_l1", "confidence_l1", "point_weights")
CUTS = ("as shipped", "without the steps", "flow and confidence", "flow")


def recorded_feeds(model_dir: Path, seq: KittiSequence) -> tuple[str, list[dict]]:
    """The flow+pose graph's name and its inputs at every pair of the sequence, tracked on onnxruntime."""
    odo = Odometry(model_dir, seq.calib, SessionConfig(backend="onnxruntime", threads=2))
    feeds: list[dict] = []
    run = odo.model.run

    def keep(stage, inputs):
        if stage == "flowpose":
            feeds.append({k: np.array(v) for k, v in inputs.items()})
        return run(stage, inputs)

    odo.model.run = keep
    for i in range(len(seq)):
        odo.step(seq.image(i), seq.scan(i), float(seq.times[i]))
    if not feeds:
        sys.exit(f"{seq.root}: no pair reached the flow+pose stage (fewer than two frames?)")
    # the graph "flowpose" opens: flowpose_weighted where the classical solve runs beside
    return odo.model._graph("flowpose"), feeds


def without_steps(model: onnx.ModelProto) -> onnx.ModelProto:
    """The graph with each solver Loop's trip count 0."""
    if not any(n.op_type == "Loop" for n in model.graph.node):
        sys.exit("this flow+pose graph has no solver Loops: the script cuts the point solver's graphs")
    m = onnx.ModelProto()
    m.CopyFrom(model)
    m.graph.initializer.append(numpy_helper.from_array(np.array(0, np.int64), "no_trips"))
    for node in m.graph.node:
        if node.op_type == "Loop":
            node.input[0] = "no_trips"
    return m


def cut_at(model: onnx.ModelProto, outputs: tuple[str, ...]) -> onnx.ModelProto:
    """The part of the graph (its solver's Loops emptied by `without_steps`) that these outputs need."""
    missing = set(outputs) - {x.name for x in model.graph.output}
    if missing:
        sys.exit(f"this flow+pose graph has no output {', '.join(sorted(missing))}")
    return Extractor(model).extract_model([i.name for i in model.graph.input], list(outputs))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq", nargs="?", type=Path, default=None)
    ap.add_argument("--onnx", type=Path, default=None)
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args()
    seq_dir = a.seq or find_real_frames()
    if seq_dir is None:
        sys.exit("no sequence: pass SEQ (../shared/data is absent)")
    model_dir = a.onnx or bundled_model_dir()
    manifest = load_manifest(model_dir)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        stage, feeds = recorded_feeds(model_dir, KittiSequence.open(seq_dir))
        sessions, names = {}, {}
        for engine in ("onnxruntime", "openvino"):
            graph = onnx.load(str(model_dir / for_engine(manifest["stages"][stage], engine)["file"]))
            bare = without_steps(graph)
            for cut, m in zip(CUTS, (graph, bare, cut_at(bare, FLOW_OUTPUTS), cut_at(bare, FLOW_OUTPUTS[:1]))):
                path = tmp / f"{engine}_{len(sessions)}.onnx"
                onnx.save(m, str(path))
                sessions[(engine, cut)] = open_session(path, SessionConfig(backend=engine, threads=2), stage)
                names[(engine, cut)] = [i.name for i in m.graph.input]
        # by each graph's input names (the cuts keep every input of the graph they come from)
        fed = {k: [{n: f[n] for n in names[k]} for f in feeds] for k in sessions}
        for k, s in sessions.items():
            for f in fed[k][:3]:
                s.run(f)
        times: dict = {k: [] for k in sessions}
        for _ in range(a.rounds):
            for i in range(len(feeds)):
                for k, s in sessions.items():
                    t = time.perf_counter()
                    s.run(fed[k][i])
                    times[k].append((time.perf_counter() - t) * 1000)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"{stage}, {len(feeds)} recorded inputs x {a.rounds} rounds, ms (median)")
    for (engine, cut), v in med.items():
        print(f"  {engine:12s} {cut:20s} {v:6.1f}")
    for engine in ("onnxruntime", "openvino"):
        shipped, bare, both, flow = (med[(engine, c)] for c in CUTS)
        print(f"  {engine}: the solver's steps {shipped - bare:.1f}, the point solver's setup {bare - both:.1f}, "
              f"the confidence {both - flow:.1f}, the flow estimator {flow:.1f}")


if __name__ == "__main__":
    try:
        main()
    except D3LVOInputError as e:  # a folder that is no model or no sequence: one line, no traceback
        sys.exit(f"error: {e}")
