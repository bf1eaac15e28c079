"""Reduced-precision variants of an exported folder: FP16 weights, or INT8 static quantisation.

INT8 uses onnxruntime's static quantisation (QDQ format, per-channel weights) calibrated on
real-format frames: each stage is calibrated with the inputs it really sees, i.e. the FP32
upstream stages' outputs on those frames. Only Conv is quantised, with unsigned 8-bit
activations (U8S8, the x86 fast path): the cost volume's GEMMs, cross attention and the pose MLP
stay FP32. Measured at 1216x352 on 2 cores (README): S8S8 with MatMul/Gemm quantised took 126 ms
per frame, U8S8 106 ms, U8S8 Conv-only 101 ms, FP32 85 ms.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import onnx

from d3lvo_deploy.backends import BESIDE_STAGE, WEIGHTED_STAGE
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.frames import FramePreprocessor
from d3lvo_deploy.manifest import load_manifest
from d3lvo_deploy.onnx_model import StageModel, camera_inputs, flowpose_feeds
from d3lvo_deploy.results import make_output_folder
from d3lvo_deploy.sequence import KittiSequence

from .onnx_export import check_graph, sha256


def calibration_feeds(fp32_dir: Path, seq_dirs: list[Path], max_frames: int = 16) -> dict[str, list[dict]]:
    """Per stage, the list of input dicts the stage receives on the calibration frames."""
    model = StageModel(fp32_dir)
    feeds: dict[str, list[dict]] = {name: [] for name in model.sessions}
    for d in seq_dirs:
        seq = KittiSequence.open(d)
        h, w = seq.image(0).shape[:2]
        pre = FramePreprocessor.for_model(seq.calib, w, h, model.config, model.depth_input)
        prev = None
        camera = camera_inputs(pre.K)  # identity start: calibration needs representative tensors, not poses
        for i in range(min(len(seq), max_frames // len(seq_dirs) + 1)):
            rgb = pre.rgb_input(seq.image(i))
            inv = sparse = pre.invdepth_input(seq.scan(i) if model.depth_input != "none" else None)
            if "completion" in model.sessions:
                feeds["completion"].append({"rgb_norm": rgb, "sparse_invdepth": inv})
                inv = model.complete(rgb, inv)
            enc_in = {"rgb_norm": rgb} | ({"invdepth": inv} if inv is not None else {})
            if model.encoder_takes_lidar:
                enc_in["sparse_invdepth"] = sparse
            feeds["encoder"].append(enc_in)
            enc = model.run("encoder", enc_in)
            if prev is not None and not model.point_solver:  # that stage is not quantized (below)
                names = model.input_names("flowpose")
                feeds["flowpose"].append(flowpose_feeds(names, prev, enc, camera))
            prev = enc
    return feeds


def _toposort(graph: onnx.GraphProto) -> None:
    ready = {i.name for i in graph.input} | {i.name for i in graph.initializer} | {""}
    pending = list(graph.node)
    ordered = []
    while pending:
        rest = []
        for n in pending:
            if all(i in ready for i in n.input):
                ordered.append(n)
                ready.update(n.output)
            else:
                rest.append(n)
        if len(rest) == len(pending):
            raise RuntimeError("graph has a cycle or a dangling input")
        pending = rest
    del graph.node[:]
    graph.node.extend(ordered)


class _Reader:
    def __init__(self, items: list[dict]):
        self.items = iter(items)

    def get_next(self):
        return next(self.items, None)


def quantize_folder(fp32_dir: Path, out_dir: Path, precision: str, calib_seqs: list[Path]) -> dict:
    """Write `precision` (fp16|int8) versions of every stage of fp32_dir into out_dir, with a manifest."""
    manifest = load_manifest(fp32_dir)
    if precision not in ("fp16", "int8"):
        raise D3LVOInputError(None, f"--precision must be fp32, fp16 or int8, not {precision!r}")
    if precision == "int8":  # before the output folder: a bad calibration sequence leaves nothing behind
        from onnxruntime.quantization import QuantFormat, QuantType, quantize_static
        from onnxruntime.quantization.shape_inference import quant_pre_process

        if not calib_seqs:
            raise D3LVOInputError(None, "INT8 needs calibration frames (--calib-seq DIR)")
        feeds = calibration_feeds(fp32_dir, calib_seqs)
    make_output_folder(out_dir, "--out", "the exported graphs")
    for name, st in manifest["stages"].items():
        src, dst = fp32_dir / st["file"], out_dir / st["file"]
        stage_precision = precision
        point_solver = manifest["model_config"].get("pose_head") == "points"
        solves = name in ("flowpose", BESIDE_STAGE, WEIGHTED_STAGE)  # the flow+pose graphs, the classical solve's
        if (precision == "fp16" and name == "flowpose" and manifest["model_config"].get("pose_head") != "mlp"
                and manifest["depth_input"] != "none") or (solves and point_solver):
            # the Gauss-Newton head stays FP32: its normal equations sum thousands of squared
            # gradients (past FP16's 65504) and its Cholesky and epsilons need more than 11 bits;
            # converted (solver nodes blocked or not) it returned non-finite poses on real frames.
            # The point solver's stage stays FP32 at INT8 too: its Conv is the image pyramid, whose
            # grey values the photometric residual compares to a few 1e-3
            stage_precision = "fp32"
            onnx.save(onnx.load(str(src)), str(dst))
        elif precision == "fp16":
            from onnxruntime.transformers.float16 import convert_float_to_float16

            m = convert_float_to_float16(onnx.load(str(src)), keep_io_types=True)
            _toposort(m.graph)  # the converter appends its input casts at the end of the node list
            onnx.save(m, str(dst))
        else:
            pre = out_dir / f"{name}.pre.onnx"
            quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
            quantize_static(str(pre), str(dst), _Reader(feeds[name]), quant_format=QuantFormat.QDQ,
                            per_channel=True, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                            op_types_to_quantize=["Conv"])
            pre.unlink()
        m = onnx.load(str(dst))
        del m.metadata_props[:]
        for p in onnx.load(str(src), load_external_data=False).metadata_props:
            m.metadata_props.append(p)
        m.metadata_props.append(onnx.StringStringEntryProto(key="d3lvo_precision", value=stage_precision))
        onnx.save(m, str(dst))
        check_graph(dst)
        manifest["stages"][name]["sha256"] = sha256(dst)
        manifest["stages"][name]["precision"] = stage_precision
        if "onnxruntime" in st:  # onnxruntime's own FP32 graph: kept where the stage stays FP32
            if stage_precision == "fp32":
                shutil.copyfile(fp32_dir / st["onnxruntime"]["file"], out_dir / st["onnxruntime"]["file"])
            else:
                del manifest["stages"][name]["onnxruntime"]
    manifest["precision"] = precision
    (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return manifest
