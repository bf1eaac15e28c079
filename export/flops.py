"""Multiply-add work of an exported graph, written into the manifest so `d3lvo bench` can report
achieved GFLOP/s per stage against the machine's GEMM peak without onnx on the vehicle.

Counts what a CPU's vector units spend their time on: Conv, ConvTranspose, MatMul and Gemm, two
FLOPs per multiply-add, from the shapes ONNX shape inference gives. Element-wise ops, gathers and
grid samples move memory rather than FLOPs and are not counted (the bench reports them as time).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import onnx.numpy_helper


def _shapes(g: onnx.GraphProto, outer: dict[str, list[int]]) -> dict[str, list[int]]:
    out = dict(outer)
    for v in list(g.value_info) + list(g.input) + list(g.output):
        dims = [d.dim_value for d in v.type.tensor_type.shape.dim]
        if dims and all(d > 0 for d in dims):
            out[v.name] = dims
    for t in g.initializer:
        out[t.name] = list(t.dims)
    return out


def loop_trips(g: onnx.GraphProto, name: str) -> int:
    """A Loop's trip-count input, where a Constant gives it (the point solver's loops)."""
    for n in g.node:
        if n.op_type == "Constant" and n.output[0] == name:
            return int(onnx.numpy_helper.to_array(n.attribute[0].t))
    raise ValueError(f"Loop trip count {name!r} is not a Constant")


def _graph_flops(g: onnx.GraphProto, outer: dict[str, list[int]]) -> float:
    shape = _shapes(g, outer)
    total = 0.0
    for n in g.node:
        ins = [shape.get(i) for i in n.input]
        outs = [shape.get(o) for o in n.output]
        if n.op_type == "Conv" and ins[1] and outs[0]:
            cout, cin_g, *k = ins[1]
            total += 2.0 * np.prod(outs[0]) * cin_g * np.prod(k)
        elif n.op_type == "ConvTranspose" and ins[0] and ins[1]:
            _, cout_g, *k = ins[1]
            total += 2.0 * np.prod(ins[0]) * cout_g * np.prod(k)
        elif n.op_type in ("MatMul", "Gemm") and ins[0] and outs[0]:
            trans_a = any(a.name == "transA" and a.i for a in n.attribute)
            k = ins[0][-2] if trans_a else ins[0][-1]
            total += 2.0 * np.prod(outs[0]) * k
        elif n.op_type == "Loop":  # every trip, as if it never stopped early: an upper bound
            total += loop_trips(g, n.input[0]) * _graph_flops(n.attribute[0].g, shape)
    return float(total)


def graph_flops(path: str | Path) -> float:
    """FLOPs of one run of the graph (batch as exported)."""
    return _graph_flops(onnx.shape_inference.infer_shapes(onnx.load(str(path))).graph, {})
