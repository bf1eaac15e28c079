"""The exported stages behind onnxruntime (or OpenVINO) sessions, checked against manifest.json.

Arrays in and out are numpy float32 NCHW: normalised RGB and inverse depth, as
d3lvo_deploy.frames.FramePreprocessor makes them (`dense_depth_m` converts to metres). `encode`
returns a dict keyed by the manifest's output names; `flow_pose` maps frame t-1's encoder outputs
(`feat_lK`, `invdepth_lK`) and frame t's (`feat_lK`) onto the flow+pose graph's inputs (`feat1_lK`,
`feat2_lK`, `invdepth1_lK`).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

# SessionConfig and the onnxruntime settings (OPT_LEVELS: GraphOptimizationLevel member names),
# re-exported for code that imports them from here
from .backends import (OPT_LEVELS, PROVIDERS, OpenVinoSession, OrtSession, SessionConfig,  # noqa: F401
                       open_session)
from .backends import BESIDE_STAGE, WEIGHTED_STAGE, stage_configs
from .backends import resolve_providers  # noqa: F401
from .errors import D3LVOInputError
from .manifest import for_engine, load_manifest
from .points import CLASSICAL_INPUT, CLASSICAL_START_INPUT, SCAN_DEPTH_INPUT

# the flow+pose inputs that are not encoder outputs (export.stages.CAMERA_INPUTS, SOLVER_INPUTS; the
# point solver's image pyramids `image1_pK`, `stack2_pK` too)
CAMERA_AND_SOLVER_INPUTS = ("intrinsics", "init_pose", "image1", "image2", "points1", "point_mask1", "image_intrinsics",
                            SCAN_DEPTH_INPUT, CLASSICAL_INPUT, CLASSICAL_START_INPUT)


def flowpose_feeds(input_names: list[str], prev: dict, cur: dict, camera: dict | None = None) -> dict:
    """Map two frames' encoder outputs (`feat_lK`, `invdepth_lK`, `grey_lK`) onto the flow+pose
    inputs (`feat1_lK`, `feat2_lK`, ...): suffix 1 is frame t-1, suffix 2 frame t. The
    Gauss-Newton head's `intrinsics` and `init_pose` come from `camera`."""
    feeds = {}
    for name in input_names:
        if name in CAMERA_AND_SOLVER_INPUTS or name.startswith(("image1_p", "stack2_p")):
            if camera is None or name not in camera:
                raise ValueError(f"the flow+pose graph needs {name!r} (a Gauss-Newton or point pose head)")
            feeds[name] = np.ascontiguousarray(camera[name], dtype=np.float32)
            continue
        frame, key = name.split("_", 1)
        feeds[name] = (prev if frame.endswith("1") else cur)[f"{frame[:-1]}_{key}"]
    return feeds


def camera_inputs(K: np.ndarray, init: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The Gauss-Newton head's extra inputs from a 3x3 camera matrix at the network input and the
    starting relative pose of the image_2 camera (identity when None)."""
    return {"intrinsics": np.array([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]]], np.float32),
            "init_pose": np.asarray(np.eye(4) if init is None else init, np.float32).reshape(1, 4, 4)}


def _point_solver(stage: dict) -> bool:
    return any(i["name"] == "points1" for i in stage.get("inputs", []))


class StageModel:
    def __init__(self, model_dir: str | Path, sc: SessionConfig = SessionConfig()):
        self.dir = Path(model_dir)
        self.manifest = load_manifest(self.dir)
        self.config = self.manifest["model_config"]
        self.depth_input = self.manifest["depth_input"]
        self.height = self.manifest["input"]["height"]
        self.width = self.manifest["input"]["width"]
        sc.check()
        sc = sc.resolved()
        self.backend = sc.backend
        self.sessions: dict[str, OrtSession | OpenVinoSession] = {}
        # the point solver: the runtime hands it both grey images and frame t-1's LiDAR point list
        self.point_solver = _point_solver(self.manifest["stages"].get("flowpose", {}))
        self.beside = False  # the classical mode solved by its own stage (`solve_classical`)
        self._settings: dict[str, SessionConfig] = {}  # each open stage's settings
        self.open_for(sc)
        # read once, not per frame: the encoder also takes the LiDAR returns (`sparse_invdepth`, for
        # the solver); the flow+pose graph is the Gauss-Newton head (takes intrinsics, init_pose)
        self.encoder_takes_lidar = "sparse_invdepth" in self.input_names("encoder")
        self.geometric = "init_pose" in self.input_names("flowpose")

    def open_for(self, sc: SessionConfig) -> list[str]:
        """Opens the stages a run with `sc` uses (`stage_configs`: with the classical mode solved
        beside the others, its stage and the flow+pose graph that takes its pose, else the flow+pose
        graph that solves both), where not open with those settings already (the bench's pipelined
        stream); returns the stages opened."""
        configs = stage_configs(self.manifest["stages"], replace(sc, backend=self.backend))
        opened = [name for name, c in configs.items() if self._settings.get(name) != c]
        for name in opened:
            self.open_stage(name, configs[name])
        self.beside = BESIDE_STAGE in configs
        return opened

    def _graph(self, stage: str) -> str:
        """The session that runs `stage`: the flow+pose stage's is `flowpose_weighted` while the
        classical mode is solved beside."""
        return WEIGHTED_STAGE if stage == "flowpose" and self.beside else stage

    def open_stage(self, stage: str, sc: SessionConfig) -> None:
        """Opens `stage`'s session on this model's engine with its settings `sc` (`stage_configs`),
        checked against the manifest."""
        st = for_engine(self.manifest["stages"][stage], self.backend)
        path = self.dir / st["file"]
        sess = open_session(path, replace(sc, backend=self.backend), stage, st)
        self._check_io(path, sess, st)
        self.sessions[stage] = sess
        self._settings[stage] = sc

    @staticmethod
    def _check_io(path: Path, sess, st: dict) -> None:
        got_in = sess.inputs
        want_in = [(i["name"], i["shape"]) for i in st["inputs"]]
        got_out = sess.outputs
        want_out = [o["name"] for o in st["outputs"]]
        norm = lambda s: [d if isinstance(d, int) else "?" for d in s]  # noqa: E731
        if [n for n, _ in got_in] != [n for n, _ in want_in] or got_out != want_out:
            raise D3LVOInputError(path, "input/output names differ from manifest.json")
        if [norm(s) for _, s in got_in] != [norm(s) for _, s in want_in]:
            raise D3LVOInputError(path, "input shapes differ from manifest.json")

    def threads(self, stage: str) -> int:
        """The engine threads `stage`'s session runs on (0: the engine's choice)."""
        return self._settings[self._graph(stage)].engine_threads

    def output_names(self, stage: str) -> list[str]:
        return self.sessions[self._graph(stage)].outputs

    def input_names(self, stage: str) -> list[str]:
        return [n for n, _ in self.sessions[self._graph(stage)].inputs]

    def run(self, stage: str, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        outs = self.sessions[self._graph(stage)].run(feeds)
        return dict(zip(self.output_names(stage), outs))

    def solve_classical(self, solver_inputs: dict[str, np.ndarray]) -> np.ndarray:
        """The classical mode's pose of the pair ((1,4,4), `CLASSICAL_INPUT`) from the flow+pose
        graph's solver inputs and `init_pose`, or `CLASSICAL_START_INPUT` where given (`Odometry`, on
        its helper thread)."""
        if CLASSICAL_START_INPUT in solver_inputs:
            solver_inputs = {**solver_inputs, "init_pose": solver_inputs[CLASSICAL_START_INPUT]}
        feeds = flowpose_feeds(self.input_names(BESIDE_STAGE), {}, {}, solver_inputs)
        return self.run(BESIDE_STAGE, feeds)[CLASSICAL_INPUT]

    def complete(self, rgb_norm: np.ndarray, sparse_inv: np.ndarray) -> np.ndarray:
        """Normalised RGB + sparse inverse depth -> dense inverse depth (see export.stages)."""
        return self.run("completion", {"rgb_norm": rgb_norm, "sparse_invdepth": sparse_inv})["dense_invdepth"]

    def encode(self, rgb_norm: np.ndarray, invdepth: np.ndarray | None,
               sparse_invdepth: np.ndarray | None = None) -> dict[str, np.ndarray]:
        feeds = {"rgb_norm": rgb_norm}
        if invdepth is not None:
            feeds["invdepth"] = invdepth
        if self.encoder_takes_lidar:
            if sparse_invdepth is None:
                raise ValueError("this encoder also takes the LiDAR returns (sparse_invdepth)")
            feeds["sparse_invdepth"] = sparse_invdepth
        return self.run("encoder", feeds)

    def dense_depth_m(self, invdepth: np.ndarray) -> np.ndarray:
        """Inverse depth (e.g. `complete`'s output) -> metres, 0 where there is none."""
        min_d = np.float32(self.config["min_depth"])
        return np.divide(min_d, invdepth, out=np.zeros_like(invdepth), where=invdepth > 0)

    def flow_pose(self, prev: dict[str, np.ndarray], cur: dict[str, np.ndarray],
                  camera: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """`camera`: `camera_inputs(K, init)`, for the Gauss-Newton head (and the point solver's
        feeds). With the classical mode solved beside (`beside`), its pose from `camera` where the
        caller solved it (`Odometry`, on another thread), else solved here first."""
        if self.beside and camera is not None and CLASSICAL_INPUT not in camera:
            camera = {**camera, CLASSICAL_INPUT: self.solve_classical(camera)}
        return self.run("flowpose", flowpose_feeds(self.input_names("flowpose"), prev, cur, camera))

    def end_profiling(self) -> list[str]:
        return [s.end_profiling() for s in self.sessions.values()]
