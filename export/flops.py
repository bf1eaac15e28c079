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


def _shapes(model: onnx.ModelProto) -> dict[str, list[int]]:
    g = onnx.shape_inference.infer_shapes(model).graph
    out: dict[str, list[int]] = {}
    for v in list(g.value_info) + list(g.input) + list(g.output):
        dims = [d.dim_value for d in v.type.tensor_type.shape.dim]
        if dims and all(d > 0 for d in dims):
            out[v.name] = dims
    for t in g.initializer:
        out[t.name] = list(t.dims)
    return out


def graph_flops(path: str | Path) -> float:
    """FLOPs of one run of the graph (batch as exported)."""
    model = onnx.load(str(path))
    shape = _shapes(model)
    total = 0.0
    for n in model.graph.node:
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
    return float(total)
