"""`d3lvo export`: checkpoint -> completion.onnx, encoder.onnx, flowpose.onnx (+ flowpose.onnxruntime.onnx) + manifest.json.

A point-solver model that also solves its classical mode gets classical.onnx and
flowpose_weighted.onnx too (each with its onnxruntime graph; `export.stages`).

Uses torch's TorchScript-based exporter (`dynamo=False`): it needs no extra package, freezes the
static shapes we want (the adaptive pooling bins are computed at export size), and emits only
standard ONNX ops for this model. Every graph is checked: `onnx.checker` with full_check, a walk
over all nodes that refuses any non-standard domain, and an onnxruntime session that loads it.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import onnx
import torch
import torch.nn.functional as F
from torch.onnx._constants import ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET

import d3lvo_deploy
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.manifest import MANIFEST_FORMAT, MANIFEST_VERSION, STANDARD_DOMAINS
from d3lvo_deploy.manifest import sha256_file as sha256
from d3lvo_deploy.points import CLASSICAL_START_INPUT, SCAN_DEPTH_INPUT
from d3lvo_deploy.results import make_output_folder
from models.checkpoint import build_model, load_checkpoint
from models.config import check_solver_settings, input_size_problem
from models.d3lvo import D3LVO
from models.layers import inverse_depth
from models.point_solver import image_pyramids, pyramid_input_names
from models.sampling import gathered
from models.pose_gn import nominal_intrinsics

from .flops import graph_flops
from .solver_loop import has_placeholders, splice_loops
from .stages import ClassicalStage, CompletionStage, EncoderStage, FlowPoseStage, splits_classical

DEFAULT_OPSET = 17  # GridSample needs 16+


@dataclass
class ExportConfig:
    out: Path
    opset: int = DEFAULT_OPSET
    height: int | None = None  # default: the checkpoint's config
    width: int | None = None
    dynamic_batch: bool = False
    # solver settings that have no weights, e.g. {"gn_points": "lidar"}: the same weights exported
    # with another Gauss-Newton configuration (to measure one against the other)
    solver: dict = field(default_factory=dict)


def all_nodes(graph: onnx.GraphProto):
    """Every node of graph, subgraphs (a Loop's body) included."""
    for n in graph.node:
        yield n
        for a in n.attribute:
            if a.g is not None and a.g.node:
                yield from all_nodes(a.g)
            for g in a.graphs:
                yield from all_nodes(g)


def non_standard_nodes(model: onnx.ModelProto) -> list[str]:
    """Every node (subgraphs included) whose domain is not the standard ONNX one."""
    return [f"{n.op_type} (domain {n.domain!r})" for n in all_nodes(model.graph) if n.domain not in STANDARD_DOMAINS]


def _io_spec(model: onnx.ModelProto) -> tuple[list[dict], list[dict]]:
    def spec(v):
        dims = [d.dim_value if d.dim_value else (d.dim_param or "?") for d in v.type.tensor_type.shape.dim]
        return {"name": v.name, "shape": dims, "dtype": onnx.helper.tensor_dtype_to_np_dtype(v.type.tensor_type.elem_type).name}

    return [spec(v) for v in model.graph.input], [spec(v) for v in model.graph.output]


def _sample_inputs(model: D3LVO, h: int, w: int) -> dict[str, tuple[torch.Tensor, ...]]:
    g = torch.Generator().manual_seed(0)
    rgb = model.normalise(torch.rand(1, 3, h, w, generator=g))
    sparse = torch.rand(1, 1, h, w, generator=g) * 60 * (torch.rand(1, 1, h, w, generator=g) > 0.93)
    inv = inverse_depth(sparse, model.cfg.min_depth)
    with torch.no_grad():
        dense = model.complete_inverse(rgb, inv) if model.cfg.uses_depth else None
        enc = EncoderStage(model)
        enc_in = (rgb, dense, inv) if model.cfg.gn_lidar else (rgb, dense) if dense is not None else (rgb,)
        enc_out = enc(*enc_in)
    enc_by = dict(zip(enc.output_names, enc_out))
    fp = FlowPoseStage(model)
    camera = {"intrinsics": nominal_intrinsics(model.cfg), "init_pose": torch.eye(4)[None],
              CLASSICAL_START_INPUT: torch.eye(4)[None]}
    if model.cfg.point_solver:
        camera.update(_solver_sample(model, h, w, g))
    flowpose = [camera[n] if n in camera else enc_by[n.replace("1_", "_").replace("2_", "_")] for n in fp.input_names]
    out = {
        "completion": (rgb, inv),
        "encoder": enc_in,
        "flowpose": tuple(flowpose),
    }
    if splits_classical(model):
        classical = ClassicalStage(model)
        out["classical"] = tuple(camera[n] for n in classical.input_names)
        with torch.no_grad():
            out["flowpose_weighted"] = (*flowpose, classical(*out["classical"]))
    return out


def _solver_sample(model: D3LVO, h: int, w: int, g: torch.Generator) -> dict[str, torch.Tensor]:
    """Point-solver inputs for tracing: a smooth random texture a little larger than the view
    (the camera's size is a dynamic axis) and points in front of it, the last half masked out."""
    H, W = h + 12, w + 14
    image = F.interpolate(torch.rand(1, 1, H // 8, W // 8, generator=g), size=(H, W), mode="bilinear")
    n = model.cfg.pt_capacity
    z = 5.0 + 30.0 * torch.rand(1, n, generator=g)
    K = nominal_intrinsics(model.cfg)
    u, v = torch.rand(1, n, generator=g) * (W - 1), torch.rand(1, n, generator=g) * (H - 1)
    pts = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[0, 3]) / K[0, 1] * z, z], -1)
    mask = (torch.arange(n) < n // 2).float()[None]
    grey1, stack2 = image_pyramids(image, torch.roll(image, 1, -1), len(model.cfg.pt_iters))
    names1, names2 = pyramid_input_names(len(model.cfg.pt_iters))
    out = {**dict(zip(names1, grey1)), **dict(zip(names2, stack2)), "points1": pts, "point_mask1": mask,
           "image_intrinsics": K}
    if model.cfg.reads_scan:  # frame t's LiDAR depth: a return on a random quarter of the pixels
        depth = 5.0 + 30.0 * torch.rand(1, 1, H, W, generator=g)
        out[SCAN_DEPTH_INPUT] = depth * (torch.rand(1, 1, H, W, generator=g) < 0.25).float()
    return out


def _export_one(module, args, path: Path, opset: int, dynamic_batch: bool) -> None:
    names = list(module.input_names) + list(module.output_names)
    dynamic = {n: {0: "batch"} for n in names} if dynamic_batch else {}
    for n in module.input_names:  # the point solver reads the camera's images at their own size
        if n.startswith(("image1_p", "stack2_p")):
            k = n.rsplit("_p", 1)[1]
            dynamic.setdefault(n, {}).update({2: f"image_height_p{k}", 3: f"image_width_p{k}"})
        if n == SCAN_DEPTH_INPUT:  # frame t's LiDAR depth, at the finest level's size
            dynamic.setdefault(n, {}).update({2: "image_height_p0", 3: "image_width_p0"})
    dynamic = dynamic or None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer/deprecation chatter; correctness is checked below
        torch.onnx.export(module, args, str(path), input_names=module.input_names, output_names=module.output_names,
                          opset_version=opset, dynamo=False, do_constant_folding=True, dynamic_axes=dynamic)
    m = onnx.load(str(path))
    if has_placeholders(m):
        onnx.save(splice_loops(m, opset, dynamic_batch), str(path))
    _declare_output_shapes(path, module, args, dynamic_batch)


def _export_stamped(module, args, path: Path, ec: ExportConfig, meta: dict[str, str]) -> onnx.ModelProto:
    """Export and stamp the metadata; `check_graph` comes after every export (`export_checkpoint`)."""
    _export_one(module, args, path, ec.opset, ec.dynamic_batch)
    m = onnx.load(str(path))
    for k, v in meta.items():
        m.metadata_props.append(onnx.StringStringEntryProto(key=k, value=v))
    onnx.save(m, str(path))
    return m


def _declare_output_shapes(path: Path, module, args, dynamic_batch: bool) -> None:
    """The exporter's shape inference gives up behind the Gauss-Newton solver's elementwise
    Cholesky (outputs named `Concatpose_dim_0`...); the shapes are static, so write the traced
    ones into the graph (batch symbolic with --dynamic-batch) for the manifest and its checks."""
    with torch.no_grad():
        outs = module(*args)
    outs = outs if isinstance(outs, tuple) else (outs,)
    m = onnx.load(str(path))
    for vi, t in zip(m.graph.output, outs):
        dims = vi.type.tensor_type.shape.dim
        for k, size in enumerate(t.shape):
            if k == 0 and dynamic_batch:
                dims[k].dim_param = "batch"
            else:
                dims[k].dim_value = int(size)
    onnx.save(m, str(path))


def check_graph(path: Path) -> onnx.ModelProto:
    model = onnx.load(str(path))
    onnx.checker.check_model(model, full_check=True)
    bad = non_standard_nodes(model)
    if bad:
        raise RuntimeError(f"{path.name} uses non-standard ops: {sorted(set(bad))}")
    import onnxruntime as ort

    ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return model


def export_checkpoint(ckpt: str | Path, ec: ExportConfig, progress=None) -> dict:
    """Export the stages and write manifest.json; returns the manifest."""
    ck = load_checkpoint(ckpt)
    cfg = ck["config"]
    h = cfg.height if ec.height is None else ec.height
    w = cfg.width if ec.width is None else ec.width
    problem = input_size_problem(h, w)
    if problem:
        raise D3LVOInputError(None, f"--height/--width: {problem}")
    if ec.opset < 16:
        raise D3LVOInputError(None, f"--opset {ec.opset}: GridSample (bilinear warping) needs opset 16 or newer")
    if ec.opset > ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET:
        raise D3LVOInputError(None, f"--opset {ec.opset}: torch {torch.__version__} exports opset 16 to "
                                    f"{ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET}")
    check_solver_settings(ec.solver)
    try:
        cfg = replace(cfg, height=h, width=w, **ec.solver)
    except (TypeError, ValueError) as e:
        raise D3LVOInputError(None, f"--set: {e}") from None
    broken = [k for k, v in ck["model"].items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if broken:  # an exported graph would compute NaN poses, or fail on an index made of them
        raise D3LVOInputError(ckpt, f"{len(broken)} weight tensors hold NaN or inf (first: {broken[0]}): the "
                                    "training diverged; export a checkpoint from before it")
    model = build_model({**ck, "config": cfg})
    out = make_output_folder(Path(ec.out), "--out", "the exported graphs")

    stages = {"completion": CompletionStage(model), "encoder": EncoderStage(model), "flowpose": FlowPoseStage(model)}
    if splits_classical(model):
        stages.update(classical=ClassicalStage(model), flowpose_weighted=FlowPoseStage(model, weighted=True))
    if not cfg.learned_completion:
        del stages["completion"]  # identity (rgb_sparse), IP-Basic in numpy, or no depth (rgb)
    inputs = _sample_inputs(model, h, w)
    # every graph is traced before any is checked: checking loads onnxruntime, and once its
    # pybind11 module is loaded every C++ exception (each exhausted pybind iterator of torch's
    # exporter) runs through its translators, which makes each later trace ~1.5x slower
    files = {name: out / f"{name}.onnx" for name in stages}
    own_files = {}
    for name, module in stages.items():
        meta = {"d3lvo_stage": name, "d3lvo_format": MANIFEST_FORMAT, "d3lvo_version": d3lvo_deploy.__version__,
                "d3lvo_config": json.dumps(cfg.to_dict()), "d3lvo_input_size": f"{w}x{h}"}
        path = files[name]
        m = _export_stamped(module.eval(), inputs[name], path, ec, meta)
        if any(n.op_type == "GridSample" for n in all_nodes(m.graph)):
            # onnxruntime's own graph: the same stage with its bilinear samples as Gathers
            own_files[name] = path.with_name(f"{name}.onnxruntime.onnx")
            with gathered():
                _export_stamped(module, inputs[name], own_files[name], ec, {**meta, "d3lvo_sampling": "gather"})
    manifest_stages = {}
    for name, path in files.items():
        ins, outs = _io_spec(check_graph(path))
        manifest_stages[name] = {"file": path.name, "sha256": sha256(path), "inputs": ins, "outputs": outs,
                                 "gflops": round(graph_flops(path) / 1e9, 4)}
        own = own_files.get(name)
        if own is not None:
            if _io_spec(check_graph(own)) != (ins, outs):
                raise RuntimeError(f"{own.name}: inputs/outputs differ from {path.name}")
            manifest_stages[name]["onnxruntime"] = {"file": own.name, "sha256": sha256(own)}
        if progress is not None:
            progress(name)

    manifest = {
        "format": MANIFEST_FORMAT,
        "version": MANIFEST_VERSION,
        "package_version": d3lvo_deploy.__version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "opset": ec.opset,
        "precision": "fp32",
        "dynamic_batch": ec.dynamic_batch,
        "model_config": cfg.to_dict(),
        "depth_input": cfg.depth_input,
        "input": {
            "width": w, "height": h,
            "rgb_norm": "float32 NCHW, (rgb / 255 - rgb_mean) / rgb_std of the RGB crop (FramePreprocessor.rgb_input)",
            "rgb_mean": list(cfg.rgb_mean), "rgb_std": list(cfg.rgb_std),
            "invdepth": f"float32 NCHW, min_depth / depth with min_depth {cfg.min_depth} m, 0 = no LiDAR return "
                        "(FramePreprocessor.invdepth_input); dense_invdepth is the same quantity",
            "camera_crop": "bottom-centre 1216x352 crop of image_2 (smaller images: largest bottom-centre crop "
                           "of the input aspect), resized to width x height; d3lvo_deploy.projection.network_view",
        },
        "pose": "T(t-1 -> t) of the image_2 camera (frame t in frame t-1 coordinates); translation m, quaternion w,x,y,z",
        "checkpoint": {"sha256": sha256(Path(ckpt)), "step": ck.get("step")},
        "stages": manifest_stages,
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return manifest
