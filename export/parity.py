"""`d3lvo parity`: torch and onnxruntime on the same real-format frames, stage by stage and chained.

Stage check: each ONNX stage gets exactly the inputs the torch stage got, so its error is its own.
Chained check: each side runs its own pipeline end to end (ORT completion feeds ORT encoder...),
and the relative poses are compared in metres and degrees, as a user would see them.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.frames import FramePreprocessor
from d3lvo_deploy.geometry import relative, rotation_angle_precise
from d3lvo_deploy.bundled import find_real_frames
from d3lvo_deploy.odometry import clean_scan
from d3lvo_deploy.onnx_model import SessionConfig, StageModel, camera_inputs, flowpose_feeds
from d3lvo_deploy.points import (CLASSICAL_NEXT_OUTPUT, CLASSICAL_START_INPUT, SCAN_DEPTH_INPUT, SolverFrame,
                                 point_config, solver_feeds)
from d3lvo_deploy.selection import SELECT_KEPT_OUTPUT, held_pose
from d3lvo_deploy.sequence import KittiSequence
from models.checkpoint import build_model, load_checkpoint
from models.config import SOLVER_KEYS, D3LVOConfig

from .onnx_export import sha256

STAGE_TOL = 1e-4  # |torch - ort| <= STAGE_TOL * max(1, |torch|): absolute for small values, relative for large
POSE_T_TOL = 1e-5  # m (float32 chains measured ~1e-6 m on the bundled model)
# deg: a float32 rotation matrix resolves ~1e-5 deg, and the point solver's 45 reweighted steps
# carry rounding differences between the engines' kernels that far (1.1e-5 deg measured over the
# real frames on the bundled model); 5e-5 deg is 0.09 mm sideways per 100 m
POSE_R_TOL = 5e-5


@dataclass
class Diff:
    max_abs: float = 0.0
    max_rel: float = 0.0
    ok: bool = True

    def update(self, ref: np.ndarray, got: np.ndarray) -> None:
        err = np.abs(ref.astype(np.float64) - got.astype(np.float64))
        mag = np.abs(ref.astype(np.float64))
        self.max_abs = max(self.max_abs, float(err.max(initial=0.0)))
        self.max_rel = max(self.max_rel, float((err / np.maximum(mag, 1e-6)).max(initial=0.0)))
        self.ok = self.ok and bool(np.all(err <= STAGE_TOL * np.maximum(1.0, mag)))


@dataclass
class ParityReport:
    frames: int
    data: str
    stages: dict[str, dict[str, Diff]] = field(default_factory=dict)
    chained_t_m: float = 0.0
    chained_r_deg: float = 0.0
    # the ONNX chain against D3LVO.forward on each pair (raw RGB in [0,1], depth in metres): no
    # export wrapper on the reference side, so a wrapper bug (frames swapped, an output mislabelled)
    # cannot cancel out
    reference_t_m: float = 0.0
    reference_r_deg: float = 0.0
    motion_t_m: float = 0.0  # size of the largest motion compared: a parity check on a model whose
    motion_r_deg: float = 0.0  # pose does not respond to its input would prove little

    @property
    def passed(self) -> bool:
        stage_ok = all(d.ok for s in self.stages.values() for d in s.values())
        return (stage_ok and self.chained_t_m <= POSE_T_TOL and self.chained_r_deg <= POSE_R_TOL
                and self.reference_t_m <= POSE_T_TOL and self.reference_r_deg <= POSE_R_TOL)

    def to_dict(self) -> dict:
        return {
            "pass": self.passed, "frames": self.frames, "data": self.data,
            "tolerances": {"stage_abs_or_rel": STAGE_TOL, "pose_t_m": POSE_T_TOL, "pose_r_deg": POSE_R_TOL},
            "stages": {s: {o: vars(d) for o, d in outs.items()} for s, outs in self.stages.items()},
            "chained": {"translation_m": self.chained_t_m, "rotation_deg": self.chained_r_deg},
            "vs_forward": {"translation_m": self.reference_t_m, "rotation_deg": self.reference_r_deg},
            "largest_motion": {"translation_m": self.motion_t_m, "rotation_deg": self.motion_r_deg},
        }


def _torch_model(ckpt: Path, manifest: dict):
    ck = load_checkpoint(ckpt)
    cfg = D3LVOConfig.from_dict(manifest["model_config"])
    # the size and the solver's settings (no weights; `d3lvo export --set`) may differ: the torch
    # model takes the export's
    free = ("height", "width", *SOLVER_KEYS)
    same = {k: v for k, v in cfg.to_dict().items() if k not in free}
    mine = {k: v for k, v in ck["config"].to_dict().items() if k not in free}
    if same != mine:
        differ = sorted(k for k in set(same) | set(mine) if same.get(k) != mine.get(k))
        raise D3LVOInputError(ckpt, f"the ONNX folder was exported with another model config (differs in: "
                                    f"{', '.join(differ[:8])}{', ...' if len(differ) > 8 else ''})")
    if manifest.get("checkpoint", {}).get("sha256") not in (None, sha256(Path(ckpt))):
        raise D3LVOInputError(ckpt, "the ONNX folder was exported from another checkpoint (sha256 differs)")
    return build_model({**ck, "config": cfg})


@torch.no_grad()
def run_parity(ckpt: str | Path, onnx_dir: str | Path, seq_dir: str | Path | None = None, frames: int = 3,
               sc: SessionConfig = SessionConfig()) -> ParityReport:
    if frames < 2:
        raise D3LVOInputError(None, f"--frames must be at least 2 (one pair), not {frames}")
    ort_model = StageModel(onnx_dir, sc)
    model = _torch_model(Path(ckpt), ort_model.manifest)
    tmp = None
    if seq_dir is None:
        seq_dir = find_real_frames()
    if seq_dir is None:
        from d3lvo_deploy.synth.generator import SynthConfig, generate

        tmp = tempfile.TemporaryDirectory(prefix="d3lvo-parity-")
        seq_dir = generate(Path(tmp.name) / "seq", SynthConfig(frames=frames, seed=123))
    seq = KittiSequence.open(seq_dir)
    n = min(frames, len(seq))
    if n < 2:
        raise D3LVOInputError(seq_dir, "parity needs at least 2 frames")
    h, w = seq.image(0).shape[:2]
    cfg = model.cfg
    pre = FramePreprocessor.for_model(seq.calib, w, h, ort_model.config, ort_model.depth_input)
    rep = ParityReport(frames=n, data=str(seq_dir))
    diff = lambda stage, name: rep.stages.setdefault(stage, {}).setdefault(name, Diff())  # noqa: E731

    prev_t = prev_o = None
    chain_t, chain_o, chain_f = [], [], []
    # each side starts the Gauss-Newton head from its own previous motion, as the runtime does
    motion_t = motion_o = motion_f = np.eye(4)  # each side's next start (`start_next` where the graph has it)
    # with `pt_classical_chain`, each side's classical solve's start: its previous `classical_next`
    chained = cfg.pt_classical_chain
    classical_t = classical_o = classical_f = None
    # with `pt_select_hold`, each side's chain holds the weighted pose as the runtime does
    left = {"t": 0, "o": 0, "f": 0}

    def kept(side: str, out: dict) -> np.ndarray:
        if not cfg.pt_select_hold:
            return np.asarray(out["matrix"][0], np.float64)
        names = ("matrix", "start_next", SELECT_KEPT_OUTPUT)
        pose, left[side] = held_pose({k: np.asarray(torch.as_tensor(out[k]).double()) for k in names}, left[side],
                                     cfg.pt_select_hold)
        return pose

    def with_classical(feeds: dict, motion: np.ndarray, classical: np.ndarray | None) -> dict:
        if chained:
            feeds[CLASSICAL_START_INPUT] = np.asarray(motion if classical is None else classical,
                                                      np.float32).reshape(1, 4, 4)
        return feeds
    K = torch.tensor([[pre.K[0, 0], pre.K[1, 1], pre.K[0, 2], pre.K[1, 2]]], dtype=torch.float32)
    raw_prev = None
    geometric = ort_model.geometric
    points = point_config(ort_model.config) if ort_model.point_solver else None
    levels = len(ort_model.config["pt_iters"]) if "stack2_p0" in ort_model.input_names("flowpose") else 0
    depth_P = seq.calib.P_velo_to_image2 if SCAN_DEPTH_INPUT in ort_model.input_names("flowpose") else None
    solver_prev = None
    for i in range(n):
        rgb = pre.rgb_input(seq.image(i))
        inv = pre.invdepth_input(seq.scan(i) if cfg.uses_depth else None)
        t_rgb = torch.from_numpy(rgb)
        t_inv = None if inv is None else torch.from_numpy(inv)
        # stage: completion (inverse depth in and out, as deployed)
        if "completion" in ort_model.sessions:
            dense_t = model.complete_inverse(t_rgb, t_inv)
            dense_o = ort_model.complete(rgb, inv)
            diff("completion", "dense_invdepth").update(dense_t.numpy(), dense_o)
            # and in metres, as a user looks at it (relative tolerance above 1 m)
            diff("completion", "dense_depth_m").update(cfg.min_depth / dense_t.numpy(), ort_model.dense_depth_m(dense_o))
        else:
            dense_t, dense_o = t_inv, inv
        # stage: encoder (same inputs), then each side's own chain
        enc_names = ort_model.output_names("encoder")
        enc_t_list = _encoder_outputs(model, t_rgb, dense_t, t_inv)
        enc_t = dict(zip(enc_names, [x.numpy() for x in enc_t_list]))
        enc_same = ort_model.encode(rgb, None if dense_t is None else dense_t.numpy(), inv)
        for k in enc_names:
            diff("encoder", k).update(enc_t[k], enc_same[k])
        enc_o = ort_model.encode(rgb, dense_o, inv)
        # the point solver's inputs are made by numpy on both sides: the same for torch and the engine
        solver_cur = None if points is None else SolverFrame.of(seq.image(i), clean_scan(seq.scan(i)),
                                                                seq.calib.T_cam2_velo, seq.calib.K2, points, levels,
                                                                depth_P)
        feeds = None if solver_prev is None else solver_feeds(solver_prev, solver_cur, seq.calib.K2, points.capacity)
        if prev_t is not None:
            cam_t = camera_inputs(pre.K, motion_t) if geometric else None
            cam_o = camera_inputs(pre.K, motion_o) if geometric else None
            if feeds is not None:
                cam_t.update(feeds)
                cam_o.update(feeds)
                with_classical(cam_t, motion_t, classical_t)
                with_classical(cam_o, motion_o, classical_o)
            fp_t = _flowpose_outputs(model, prev_t, enc_t, cam_t)
            fp_same = ort_model.flow_pose(prev_t, enc_t, cam_t)
            for k in fp_t:
                diff("flowpose", k).update(fp_t[k], fp_same[k])
            motion_t = fp_t.get("start_next", fp_t["matrix"])[0].astype(np.float64)
            out_o = ort_model.flow_pose(prev_o, enc_o, cam_o)
            motion_o = out_o.get("start_next", out_o["matrix"])[0].astype(np.float64)
            if chained:
                classical_t = fp_t[CLASSICAL_NEXT_OUTPUT][0].astype(np.float64)
                classical_o = out_o[CLASSICAL_NEXT_OUTPUT][0].astype(np.float64)
            chain_t.append(kept("t", fp_t))
            chain_o.append(kept("o", out_o))
        raw = _forward_inputs(pre, seq, i, cfg)
        if raw_prev is not None:
            init = torch.from_numpy(motion_f.astype(np.float32))[None] if geometric else None
            solver = None if feeds is None else {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in
                                                 with_classical(dict(feeds), motion_f, classical_f).items()}
            fwd = model(raw_prev[0], raw[0], raw_prev[1], raw[1], K if geometric else None, init, solver)
            motion_f = fwd.get("start_next", fwd["matrix"])[0].double().numpy()
            if chained:
                classical_f = fwd[CLASSICAL_NEXT_OUTPUT][0].double().numpy()
            # the engine's flows and confidences against forward's, output by output
            for lvl, f in zip(cfg.flow_levels, fwd["flows"]):
                diff("vs_forward", f"flow_l{lvl}").update(f.numpy(), out_o[f"flow_l{lvl}"])
            conf_levels = (cfg.flow_levels[-1],) if cfg.point_solver else cfg.gn_levels
            for lvl, c in zip(conf_levels if "confidence" in fwd else (), fwd.get("confidence", [])):
                diff("vs_forward", f"confidence_l{lvl}").update(c.numpy(), out_o[f"confidence_l{lvl}"])
            chain_f.append(kept("f", fwd))
        prev_t, prev_o, raw_prev, solver_prev = enc_t, enc_o, raw, solver_cur
    rep.chained_t_m, rep.chained_r_deg = _largest_motion(relative(np.array(chain_t), np.array(chain_o)))
    rep.reference_t_m, rep.reference_r_deg = _largest_motion(relative(np.array(chain_f), np.array(chain_o)))
    rep.motion_t_m, rep.motion_r_deg = _largest_motion(np.array(chain_f))
    if tmp is not None:
        tmp.cleanup()
    return rep


def _largest_motion(T: np.ndarray) -> tuple[float, float]:
    """Largest translation (m) and rotation (deg) among (N,4,4) motions."""
    return (float(np.linalg.norm(T[:, :3, 3], axis=1).max()),
            float(np.degrees(rotation_angle_precise(T[:, :3, :3])).max()))


def _forward_inputs(pre: FramePreprocessor, seq: KittiSequence, i: int, cfg) -> tuple:
    """D3LVO.forward's own inputs: RGB in [0,1] NCHW and depth in metres (None in rgb mode)."""
    rgb = torch.from_numpy(pre.rgb(seq.image(i))).permute(2, 0, 1)[None].contiguous()
    depth = torch.from_numpy(pre.depth(seq.scan(i)))[None, None] if cfg.uses_depth else None
    return rgb, depth


def _encoder_outputs(model, rgb, dense, sparse) -> list[torch.Tensor]:
    from .stages import EncoderStage

    enc = EncoderStage(model)
    args = (rgb, dense, sparse) if model.cfg.gn_lidar else (rgb, dense) if dense is not None else (rgb,)
    return list(enc(*args))


def _flowpose_outputs(model, prev: dict, cur: dict, camera: dict | None) -> dict[str, np.ndarray]:
    from .stages import FlowPoseStage

    fp = FlowPoseStage(model)
    feeds = flowpose_feeds(fp.input_names, prev, cur, camera)
    return dict(zip(fp.output_names, [x.numpy() for x in fp(*(torch.from_numpy(feeds[n]) for n in fp.input_names))]))
