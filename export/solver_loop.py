"""The point solver's steps as ONNX Loops that end when a level has converged.

Traced, the solver would be 45 unrolled Gauss-Newton steps, each computed even after its level
has stopped (a step then multiplies to zero). The trace instead holds one placeholder node per
level (`models.point_solver._GaussNewtonLoop`); here each becomes a standard `Loop` whose body is
`point_solver.gn_steps` exported on its own (one block of `scale_every` steps, so that the
Huber threshold is re-estimated where the unrolled steps re-estimate it) and whose condition is
"some level of the batch still moves". The outputs equal the unrolled graph's; the time saved
is the blocks after convergence (docs/performance.md).
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper
from torch import nn

from models.point_solver import LOOP_DOMAIN, LOOP_OP, SolverSettings, gn_steps
from models.sampling import gathering, inside_lattice

BODY_INPUTS = ("P", "active", "Xh", "ref", "stack", "G", "f", "weight", "w_ok", "median_mask", "half", "last_cell",
               "row_map", "offsets")
CARRIED = 2  # P and active are carried from block to block; the rest are read from the outer graph


class _Block(nn.Module):
    def __init__(self, s: SolverSettings, layout: tuple[int, int, int]):
        super().__init__()
        self.s, self.layout = s, layout

    def forward(self, *tensors):
        return gn_steps(*tensors, self.s.scale_every, self.s, self.layout)


def block_graph(s: SolverSettings, capacity: int, opset: int, dynamic_batch: bool, batch: int = 1,
                images: int | None = None) -> onnx.GraphProto:
    """One block of `s.scale_every` steps as a graph with inputs BODY_INPUTS and outputs (P, active)
    for `batch` solves of `images` pairs (the placeholder's, default `batch`: each solve its own
    image stack; dynamic with dynamic_batch); the camera image's size is dynamic, as in the
    flow+pose graph."""
    g = torch.Generator().manual_seed(0)
    n, h, w, b = capacity, 40, 60, batch
    m = batch if images is None else images
    args = (torch.eye(3, 4).expand(b, 3, 4), torch.ones(b, 1, 1),
            torch.cat([torch.rand(b, 2, n, generator=g), 5 + torch.rand(b, 1, n, generator=g), torch.ones(b, 1, n)], 1),
            torch.rand(b, 1, n, generator=g), torch.rand(m, 3, h, w, generator=g), torch.eye(3).expand(b, 3, 3) * 0.1,
            torch.full((b, 2, 1), 50.0), torch.ones(b, 1, n), torch.ones(b, 1, n), torch.ones(b, 1, n),
            *inside_lattice(torch.zeros(m, 3, h, w), torch.zeros(b)))
    dynamic = {"stack": {2: "image_height", 3: "image_width"}}
    if dynamic_batch:
        for name in BODY_INPUTS + ("P_next", "active_next"):
            dynamic.setdefault(name, {})[0] = "pairs" if name == "stack" and m != b else "batch"
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        path = Path(tmp) / "block.onnx"
        torch.onnx.export(_Block(s, (b // m, 3, n)).eval(), args, str(path), input_names=list(BODY_INPUTS),
                          output_names=["P_next", "active_next"], opset_version=opset, dynamo=False,
                          do_constant_folding=True, dynamic_axes=dynamic)
        return onnx.load(str(path)).graph


def _renamed_body(block: onnx.GraphProto, outer: list[str], prefix: str) -> onnx.GraphProto:
    """The block as a Loop body: inputs (iteration, condition, P, active), the other BODY_INPUTS read
    from the outer graph's values `outer`, every other name prefixed (a subgraph may not reuse an
    outer name), initializers as Constant nodes, and the condition 'any active' first among the
    outputs."""
    names = {b: o for b, o in zip(BODY_INPUTS[CARRIED:], outer)}

    def name(v: str) -> str:
        return v if v == "" else names.get(v, prefix + v)

    nodes = [helper.make_node("Constant", [], [name(t.name)], value=t) for t in block.initializer]
    for node in block.node:
        new = onnx.NodeProto()
        new.CopyFrom(node)
        new.name = prefix + node.name
        new.input[:] = [name(v) for v in node.input]
        new.output[:] = [name(v) for v in node.output]
        nodes.append(new)
    p_next, active_next = (name(o.name) for o in block.output)
    nodes += [helper.make_node("ReduceMax", [active_next], [prefix + "most_active"], keepdims=0),
              helper.make_node("Constant", [], [prefix + "zero"], value=numpy_helper.from_array(np.zeros((), np.float32))),
              helper.make_node("Greater", [prefix + "most_active", prefix + "zero"], [prefix + "cond_out"])]
    carried_in = {i.name: i for i in block.input}
    inputs = [helper.make_tensor_value_info(prefix + "iteration", TensorProto.INT64, []),
              helper.make_tensor_value_info(prefix + "cond_in", TensorProto.BOOL, [])]
    for b in BODY_INPUTS[:CARRIED]:
        vi = onnx.ValueInfoProto()
        vi.CopyFrom(carried_in[b])
        vi.name = prefix + b
        inputs.append(vi)
    outputs = [helper.make_tensor_value_info(prefix + "cond_out", TensorProto.BOOL, [])]
    for o in block.output:
        vi = onnx.ValueInfoProto()
        vi.CopyFrom(o)
        vi.name = name(o.name)
        outputs.append(vi)
    return helper.make_graph(nodes, prefix + "gauss_newton_block", inputs, outputs)


def _is_placeholder(node: onnx.NodeProto) -> bool:
    return node.domain == LOOP_DOMAIN and node.op_type == LOOP_OP


def has_placeholders(model: onnx.ModelProto) -> bool:
    return any(_is_placeholder(n) for n in model.graph.node)


def _read_by(nodes) -> set[str]:
    """Every value the nodes read, their Loop bodies' outer-scope reads included."""
    names = set()
    for n in nodes:
        names.update(n.input)
        for a in n.attribute:
            if a.type == onnx.AttributeProto.GRAPH:
                names |= _read_by(a.g.node) | {o.name for o in a.g.output}
    return names


def _used(nodes: list, graph: onnx.GraphProto) -> list:
    """The nodes that the graph's outputs depend on: a Loop reads from the outer graph only what
    its body uses, so the sampling lattice that OpenVINO's graph (GridSample) does not use is
    dropped here rather than left to each engine."""
    needed = {o.name for o in graph.output}
    kept = []
    for n in reversed(nodes):
        if any(o in needed for o in n.output):
            kept.append(n)
            needed |= _read_by([n])
    return kept[::-1]


# the blocks exported so far in this process (read only), by everything that shapes one (the
# placeholder's settings, the opset, the batch axis and the sampling layout): each costs a torch
# export, and a model's levels and its later exports in one process (other solver settings, the
# tests, `d3lvo bench --ckpt`) share them
_BLOCKS: dict[tuple, onnx.GraphProto] = {}


def splice_loops(model: onnx.ModelProto, opset: int, dynamic_batch: bool) -> onnx.ModelProto:
    """Every placeholder node -> Loop(max trips, true, P, active) over a block of its settings'
    steps; drops the placeholder's opset import, so that the graph holds standard ops only."""
    nodes = []
    loops = 0
    for node in model.graph.node:
        if not _is_placeholder(node):
            nodes.append(node)
            continue
        a = {x.name: helper.get_attribute_value(x) for x in node.attribute}
        batch = a.get("batch", 1)
        images = a.get("images", batch)
        affine = bool(a.get("affine", 0))
        stride = a.get("stride", 1)
        key = (a["block"], a["stop"], a["damping"], a["capacity"], batch, images, affine, stride, opset,
               dynamic_batch, gathering())
        if key not in _BLOCKS:
            s = SolverSettings(stop_step=a["stop"], damping=a["damping"], scale_every=a["block"], affine=affine,
                               median_stride=stride)
            _BLOCKS[key] = block_graph(s, a["capacity"], opset, dynamic_batch, batch, images)
        trips = a["trips"]
        prefix = f"gn_loop{loops}/"
        loops += 1
        body = _renamed_body(_BLOCKS[key], list(node.input[CARRIED:]), prefix)
        nodes += [helper.make_node("Constant", [], [prefix + "trips"], value=helper.make_tensor(
                      prefix + "trips", TensorProto.INT64, [], [trips])),
                  helper.make_node("Constant", [], [prefix + "start"], value=helper.make_tensor(
                      prefix + "start", TensorProto.BOOL, [], [True])),
                  helper.make_node("Loop", [prefix + "trips", prefix + "start", *node.input[:CARRIED]],
                                   list(node.output), name=prefix + "Loop", body=body)]
    del model.graph.node[:]
    model.graph.node.extend(_used(nodes, model.graph))
    keep = [o for o in model.opset_import if o.domain != LOOP_DOMAIN]
    del model.opset_import[:]
    model.opset_import.extend(keep)
    return model
