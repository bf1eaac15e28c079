"""Streaming odometry for robot integration: `Odometry(model_dir, calib).step(image, points) -> pose`.

Each frame is preprocessed, completed and encoded exactly once; its encoder outputs are kept as
frame t-1 of the next pair. Poses are cam0 poses (KITTI convention), first frame = identity.
"""

from __future__ import annotations

import functools
import numbers
import os
import time
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .blas import one_blas_thread
from .calib import Calib, check_fit, parse_calib
from .cold_start import ColdStartConfig
from .errors import D3LVOInputError
from .frames import FramePreprocessor
from .geometry import change_frame, is_rigid, relative
from .motion_guard import MotionGuard, guard_motion, scaled_motion
from .onnx_model import BESIDE_STAGE, SessionConfig, StageModel, camera_inputs
from .points import (CLASSICAL_INPUT, CLASSICAL_NEXT_OUTPUT, CLASSICAL_START_INPUT, SCAN_DEPTH_INPUT, SolverFrame,
                     finest_level, in_depth_range, point_config, solver_feeds, textured_points)
from .projection import PROJECTION_MIN_DEPTH, rows_in_view, sparse_depth
from .selection import SELECT_KEPT_OUTPUT, held_pose

STAGES = ("project", "completion", "encoder", "flowpose")
# a frame's stage that runs on another thread beside those (`FrameTiming.beside`), as the tables name it
BESIDE_ROW = "classical (beside)"


class ScanWarning(UserWarning):
    """A scan was empty or had NaN points; the documented fallback was used."""


class FrameSizeError(D3LVOInputError):
    """A frame of another size than the run's first: a run names the frame's image file."""


def check_frame_size(image: np.ndarray, width: int, height: int) -> None:
    """A tracker's calibration is one camera's: a frame of another size is another camera."""
    h, w = image.shape[:2]
    if (w, h) != (width, height):
        raise FrameSizeError(None, f"image is {w}x{h}, earlier frames were {width}x{height}")


# a scan's columns: x y z, then intensity and whatever else a driver writes (ring, time, ...);
# at most this many rows against more columns is a scan passed transposed
TRANSPOSED_ROWS = 6


def check_image(image) -> None:
    """A frame the trackers take: an (H,W,3) uint8 RGB array."""
    if not isinstance(image, np.ndarray):
        raise D3LVOInputError(None, f"image must be an (H,W,3) uint8 RGB numpy array, got {type(image).__name__}")
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise D3LVOInputError(None, f"image must be (H,W,3) uint8 RGB, got {image.dtype} {image.shape}")


def as_calib(calib) -> Calib:
    """A Calib, or one read from the calibration file a path names."""
    if not isinstance(calib, (Calib, str, os.PathLike)):
        raise D3LVOInputError(None, f"calib must be a Calib or the path of a calibration file, got "
                                    f"{type(calib).__name__}")
    return calib if isinstance(calib, Calib) else parse_calib(calib)


def calib_source(given) -> str | Path:
    """What the first frame's check names: the calibration file, or a Calib built by hand."""
    return "the calibration" if isinstance(given, Calib) else Path(given)


def check_first_frame(tracker, image: np.ndarray, scan: np.ndarray | None) -> None:
    """A tracker's first frame against its calibration (`calib.check_fit`), once: images and
    scans it cannot be for. `d3lvo run` checks the recording before and sets `fit_checked`."""
    if not tracker.fit_checked:
        check_fit(tracker.calib, image.shape[1], image.shape[0], scan if scan is not None else np.zeros((0, 3)),
                  tracker.calib_source, "0")
        tracker.fit_checked = True


def as_stamp(stamp, what: str = "stamp") -> float | None:
    """A frame's time in seconds (None where none is given): a NaN, inf or non-number would reach
    the constant-velocity start as NaN or an absurd scale, so it is one error at the call."""
    if stamp is None:
        return None
    if isinstance(stamp, (str, bytes, bool)) or not isinstance(stamp, (numbers.Real, np.floating, np.integer)):
        raise D3LVOInputError(None, f"{what} must be a time in seconds (a number), not {stamp!r}")
    if not np.isfinite(stamp):
        raise D3LVOInputError(None, f"{what} must be a finite time in seconds, not {stamp!r}")
    return float(stamp)


def rigid_pose(pose, what: str) -> np.ndarray:
    """A 4x4 float64 copy of `pose`, or one error naming `what`: a NaN or a 3x3 given as a pose
    would otherwise turn every later pose into NaN, or fail at a later step."""
    try:
        T = np.array(pose, dtype=np.float64)
    except (TypeError, ValueError):
        raise D3LVOInputError(None, f"{what} must be a 4x4 pose matrix, got {type(pose).__name__}") from None
    if T.shape != (4, 4):
        raise D3LVOInputError(None, f"{what} must be a 4x4 pose matrix, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise D3LVOInputError(None, f"{what} has NaN or inf entries")
    if not is_rigid(T) or np.linalg.det(T[:3, :3]) <= 0:
        raise D3LVOInputError(None, f"{what} is not a rigid transform (rotation block not a rotation, or last row "
                                    "not 0 0 0 1)")
    return T


def clean_scan(points: np.ndarray | None, source: str = "scan") -> np.ndarray:
    """Drop points with a non-finite x, y or z (a non-finite reflectance becomes 0). An empty (or
    None) scan is allowed: the frame then has no LiDAR depth and the completion stage works from
    the image alone (documented fallback), with a warning."""
    if points is None:
        points = np.zeros((0, 4), np.float32)
    kind = points.dtype.kind if isinstance(points, np.ndarray) and points.ndim else "f"  # else: the checks below
    if kind in "USb" and len(points):  # text read as numbers, or booleans: not a scan
        raise D3LVOInputError(None, f"{source}: points must be a numeric (N,4) array (x, y, z, intensity), "
                                    f"got an array of {points.dtype}")
    if kind in "iu" and len(points):  # whole metres: the solver's points a metre off, where it reads them
        warnings.warn(f"{source}: integer coordinates ({points.dtype}): LiDAR points in metres are float32; "
                      "these are taken as given", ScanWarning, stacklevel=3)
    try:
        pts = np.asarray(points, dtype=np.float32)
    except (TypeError, ValueError):
        got = f"an array of {points.dtype}" if isinstance(points, np.ndarray) else type(points).__name__
        raise D3LVOInputError(None, f"{source}: points must be a numeric (N,4) array (x, y, z, intensity), "
                                    f"got {got}") from None
    transposed = pts.ndim == 2 and 3 <= pts.shape[0] <= TRANSPOSED_ROWS < pts.shape[1]
    if pts.ndim != 2 or pts.shape[1] < 3 or transposed:
        hint = " (transposed? a scan is one point per row)" if transposed else ""
        raise D3LVOInputError(None, f"{source}: points must be an (N,3) or (N,4) array (x y z first; further "
                                    f"columns are ignored), got shape {pts.shape}{hint}")
    # per coordinate, not np.all(..., axis=1): that reduction over rows of 3 took 2.1 ms per scan, this 0.15
    finite = np.isfinite(pts[:, 0]) & np.isfinite(pts[:, 1]) & np.isfinite(pts[:, 2])
    if not finite.all():
        warnings.warn(f"{source}: dropped {int((~finite).sum())} of {len(pts)} points with NaN/inf", ScanWarning,
                      stacklevel=3)
        pts = pts[finite]
    if pts.shape[1] > 3 and not np.isfinite(pts[:, 3:]).all():
        # reflectance and further columns are read by nothing, but the view cull's GEMM takes whole
        # rows (`rows_in_view`: 0 x NaN is NaN), so a NaN there would drop the point: 0 in a copy
        pts = pts.copy()
        pts[:, 3:][~np.isfinite(pts[:, 3:])] = 0.0
    if len(pts) == 0:
        warnings.warn(f"{source}: no LiDAR points; this frame runs without depth input, and a point solver, which "
                      "tracks this frame's points into the next one, keeps that pair's starting motion (the last "
                      "pair's; none on the first)", ScanWarning, stacklevel=3)
    return pts


# with at least this many returns in view and none of them on texture, the image is blank: worth a word
BLANK_IMAGE_RETURNS = 100


def check_texture(textured: np.ndarray, in_view: np.ndarray | None, cfg, T_cam_velo: np.ndarray, source: str) -> None:
    """A warning where the solver has no point of this frame to track though its scan has returns
    around the view: none within the solver's depth range (a scan in millimetres after the first
    frame, which `check_fit` reads), or none on image texture (a black, blank or overexposed
    frame). The pairs with this frame keep their starting motion, which a run would otherwise
    write without a word. `cfg`: the solver's `PointConfig`."""
    if len(textured) or in_view is None or len(in_view) < BLANK_IMAGE_RETURNS:
        return
    near = len(in_depth_range(in_view, T_cam_velo, cfg.min_depth, cfg.max_depth))
    if near < BLANK_IMAGE_RETURNS:
        warnings.warn(f"{source}: {near} of its {len(in_view)} returns in and around the view lie within "
                      f"{cfg.min_depth:g}-{cfg.max_depth:g} m of the camera: not in metres (millimetres?)? The pairs "
                      "with this frame keep their starting motion (the last pair's; none on the first)", ScanWarning,
                      stacklevel=4)
    else:
        image = source.removesuffix("'s scan") + "'s image" if source.endswith("'s scan") else "image"
        warnings.warn(f"{image}: no texture where the scan's {near} returns in and around it land (grey gradient "
                      f"above {cfg.min_gradient:g}): black, blank or overexposed? The pairs with this frame keep their "
                      "starting motion (the last pair's; none on the first)", ScanWarning, stacklevel=4)


@dataclass
class PreparedFrame:
    image: np.ndarray  # the camera image as read (the --viz panels show it)
    rgb: np.ndarray  # (1,3,h,w) network input
    inv: np.ndarray | None  # (1,1,h,w) sparse inverse depth (or IP-Basic's), None in rgb mode
    solver: SolverFrame | None  # the point solver's grey image and points
    project_ms: float
    stamp: float | None = None  # the frame's time in seconds (the motion guard's dt), if known


@dataclass
class FrameTiming:
    ms: dict[str, float] = field(default_factory=dict)
    # stages that ran on another thread beside those in `ms` (the classical solve beside completion
    # and encoder): their time is in the frame's wall time only where the flow+pose stage waited
    # for them, and so in its figure
    beside: dict[str, float] = field(default_factory=dict)

    @property
    def total(self) -> float:
        return sum(self.ms.values())

    @property
    def rows(self) -> dict[str, float]:
        """The stage times as the latency tables list them: `ms`, and the time beside as `BESIDE_ROW`."""
        return {**self.ms, **({BESIDE_ROW: sum(self.beside.values())} if self.beside else {})}


class Odometry:
    """Minimal robot-facing API. `calib` is a Calib or a path to a KITTI calib file."""

    scan_source = "scan"  # what a scan warning names (`d3lvo run` sets the frame)

    def __init__(self, model_dir: str | Path, calib: Calib | str | Path, sc: SessionConfig = SessionConfig(),
                 model: StageModel | None = None, cold_start: ColdStartConfig = ColdStartConfig(),
                 guard: MotionGuard = MotionGuard()):
        self.calib = as_calib(calib)  # before the model loads
        self.cold_start = cold_start
        self.guard = guard
        self.model = model if model is not None else StageModel(model_dir, sc)
        self.calib_source, self.fit_checked = calib_source(calib), False  # `check_first_frame`
        self.pre: FramePreprocessor | None = None
        self.last_timing = FrameTiming()
        self.keep_outputs = False  # keep the last frame's intermediate tensors in `last` (for --viz)
        self.last: dict = {}
        self.points = point_config(self.model.config) if self.model.point_solver else None
        # a graph that takes the solver's image pyramids (rather than building them) gets them from
        # `prepare`, made once per frame
        takes_pyramids = "stack2_p0" in self.model.input_names("flowpose")
        self.pyramid_levels = len(self.model.config["pt_iters"]) if takes_pyramids else 0
        # and one that checks the finest level's restart against frame t's scan, its LiDAR depth
        self.takes_depth = SCAN_DEPTH_INPUT in self.model.input_names("flowpose")
        # `pt_select_hold`: the weighted pose held on this many pairs after each the graph keeps it on
        self.hold = int(self.model.config.get("pt_select_hold", 0) or 0)
        if self.hold and SELECT_KEPT_OUTPUT not in self.model.output_names("flowpose"):
            raise D3LVOInputError(self.model.dir / "manifest.json", f"sets pt_select_hold {self.hold} but its flow+pose "
                                  f"graph has no `{SELECT_KEPT_OUTPUT}` output: export the model again")
        self.prepare_threads = sc.preparing_threads  # `prepare`'s threads (the session setting resolved)
        # `prepare`'s second thread: started by the first job given to it; it ends when the
        # executor is collected with this object
        self._helper = ThreadPoolExecutor(1, thread_name_prefix="d3lvo-prepare")
        self.reset()

    @property
    def needs_scan(self) -> bool:
        return self.model.depth_input != "none"

    @property
    def keeps_own_start(self) -> bool:
        """The next pair's start is not the last pose's motion: a resumed run needs `motion2`
        saved beside the poses (`d3lvo_deploy.pipeline`)."""
        return "start_next" in self.model.output_names("flowpose")

    @property
    def chains_classical(self) -> bool:
        """The graph's classical solve starts from the previous classical pose (`pt_classical_chain`)."""
        return CLASSICAL_NEXT_OUTPUT in self.model.output_names("flowpose")

    def start_state(self) -> np.ndarray:
        """(K,4,4) where the next pair starts: `motion2`, and the classical solve's own start where
        the graph `chains_classical`; what a resumed run needs (`prime`'s `start`)."""
        if not self.chains_classical:
            return self.motion2[None]
        return np.stack([self.motion2, self._classical_start])

    @property
    def _classical_start(self) -> np.ndarray:
        """Where the classical solve starts after a pair: its own previous pose, else (none saved)
        where the weighted solve starts."""
        return self.motion2 if self.motion2_classical is None else self.motion2_classical

    def reset(self, start_pose: np.ndarray | None = None) -> None:
        """Forget the previous frame; the next `step` returns `start_pose` (identity)."""
        self._prev: dict[str, np.ndarray] | None = None
        self.pose = np.eye(4) if start_pose is None else rigid_pose(start_pose, "reset's start_pose")
        self.relative = np.eye(4)
        # the last pair's motion of the image_2 camera: where the Gauss-Newton head starts the next
        # pair (constant velocity; on the first pair identity, or for a point-solver graph
        # `cold_start_motion`). A graph with
        # `start_next` (`keeps_own_start`) says where instead: its weighted pose, which its kept pose
        # need not be
        self.motion2 = np.eye(4)
        # with `chains_classical`: the previous classical pose, where the classical solve starts
        # (None before the first pair, which starts both solves alike)
        self.motion2_classical: np.ndarray | None = None
        self.cold = True  # no previous motion yet
        self.fit_checked = False  # a reset may start another recording: its first frame is checked again
        self.frames = 0
        self.hold_left = 0  # `hold`: pairs left on which the weighted pose is kept whatever the graph chose
        # the motion guard's state: the last kept image_2 motion (None until a pair has one), its
        # time, and how many pairs the guard replaced
        self.kept2: np.ndarray | None = None
        self.kept_dt = self.guard.period
        self.guarded = 0

    def _preprocessor(self, image: np.ndarray) -> FramePreprocessor:
        h, w = image.shape[:2]
        if self.pre is None:
            self.pre = FramePreprocessor.for_model(self.calib, w, h, self.model.config, self.model.depth_input)
        else:
            check_frame_size(image, self.pre.view.src_width, self.pre.view.src_height)
        return self.pre

    def prepare(self, image: np.ndarray, points: np.ndarray | None, threads: int | None = None,
                stamp: float | None = None) -> "PreparedFrame":
        """The CPU half of a frame, before any network: RGB input, LiDAR projection and IP-Basic,
        the solver's points. Independent of the previous frame, so a pipeline runs it for frame
        t+1 on another thread while the network works on frame t (after the first frame, which
        fixes the view), with `threads` 1. With 2 (`threads` defaults to `self.prepare_threads`,
        from `SessionConfig.preparing_threads`) the solver's frame is made on a second thread
        beside the network's inputs; the same arrays either way. `stamp`: the frame's time in
        seconds, for the motion guard (frames `MotionGuard.period` apart where not given)."""
        check_image(image)
        with one_blas_thread():  # no BLAS threads left spinning beside the engine (`blas`)
            frame = self._prepare(image, points, self.prepare_threads if threads is None else threads)
        frame.stamp = as_stamp(stamp)
        return frame

    def _beside(self, job: Callable[[], Any], threads: int) -> Callable[[], Any]:
        """What gives `job`'s result: with `threads` > 1 the job starts now on the helper thread
        (numpy and OpenCV release the GIL, so both threads compute; jobs run in the order given,
        so a job may wait for an earlier one); with one thread it runs when its result is first
        asked for."""
        if threads < 2:
            return functools.cache(job)
        return self._helper.submit(job).result

    def _prepare(self, image: np.ndarray, points: np.ndarray | None, threads: int) -> "PreparedFrame":
        t0 = time.perf_counter()
        pre = self._preprocessor(image)
        scan = clean_scan(points, self.scan_source) if self.model.depth_input != "none" else None  # checked before any job starts
        check_first_frame(self, image, scan)
        # the solver's finest level (the camera's grey image and its gradients) needs no scan: it
        # starts at once, beside the scan's cull
        finest = self._beside(functools.partial(finest_level, image), threads) if self.model.point_solver else None
        h, w = image.shape[:2]
        if scan is not None and len(scan):  # one cull for both passes below (`rows_in_view`)
            scan = rows_in_view(scan, self.calib.P_velo_to_image2, w, h,
                                min(PROJECTION_MIN_DEPTH, self.points.min_depth if self.points is not None else np.inf))
        textured = None
        if finest is not None:  # the textured returns, beside the network's inputs
            textured = self._beside(functools.partial(self._textured, finest, scan), threads)
        rgb = pre.rgb_input(image)
        inv = pre.invdepth_input(scan)
        solver = None
        if textured is not None:
            depth = sparse_depth(scan, self.calib.P_velo_to_image2, w, h) if self.takes_depth else None
            solver = SolverFrame.assemble(finest(), textured(), self.pyramid_levels, depth)
            check_texture(solver.points, scan, self.points, self.calib.T_cam2_velo, self.scan_source)
        return PreparedFrame(image, rgb, inv, solver, (time.perf_counter() - t0) * 1000)

    def _textured(self, finest: Callable[[], np.ndarray], scan: np.ndarray) -> np.ndarray:
        stack = finest()
        return textured_points(scan, self.calib.T_cam2_velo, self.calib.K2, stack[0], self.points, (stack[1], stack[2]))

    def encode(self, image: np.ndarray, points: np.ndarray | None, stamp: float | None = None) -> dict[str, np.ndarray]:
        """Frame -> encoder outputs (the per-frame half of the work)."""
        return self.encode_prepared(self.prepare(image, points, stamp=stamp))

    def encode_prepared(self, frame: "PreparedFrame") -> dict[str, np.ndarray]:
        enc, t = self.encode_timed(frame)
        self.last_timing = FrameTiming(t)
        return enc

    def encode_timed(self, frame: "PreparedFrame") -> tuple[dict[str, np.ndarray], dict[str, float]]:
        """`encode_prepared` with its stage times returned rather than kept in `last_timing`: a
        three-deep pipeline's reader thread encodes frame t+1 with it while this thread runs frame
        t's flow+pose stage (`step_encoded`)."""
        t = {"project": frame.project_ms}
        t0 = time.perf_counter()
        rgb, inv = frame.rgb, frame.inv
        if self.keep_outputs:
            self.last = {"image": self.pre.view.apply_image(frame.image), "sparse_invdepth": inv}
        sparse = inv
        if "completion" in self.model.sessions:
            inv = self.model.complete(rgb, inv)
        if self.keep_outputs:
            self.last["dense_invdepth"] = inv
        t["completion"] = (time.perf_counter() - t0) * 1000
        t0 = time.perf_counter()
        enc = self.model.encode(rgb, inv, sparse)
        t["encoder"] = (time.perf_counter() - t0) * 1000
        if frame.solver is not None:
            enc["solver_frame"] = frame.solver
        enc["stamp"] = frame.stamp
        return enc, t

    def step(self, image: np.ndarray, points: np.ndarray | None, stamp: float | None = None) -> np.ndarray:
        """Add a frame; returns its 4x4 cam0 pose in the first frame's coordinates. `stamp`: its time
        in seconds (the sensor's), which the motion guard reads; without, frames are taken to be
        `MotionGuard.period` apart."""
        return self.step_prepared(self.prepare(image, points, stamp=stamp))

    def step_prepared(self, frame: "PreparedFrame", on_encoded: Callable[[], None] | None = None) -> np.ndarray:
        """`step` on a frame `prepare` has already done (by a pipeline's reader thread).
        `on_encoded` runs between the encoder and the flow+pose stage: a pipeline starts preparing
        the next frame there, beside the solver (one thread on OpenVINO), rather than beside completion
        and encoder, which use every core. Where the model solves its classical mode beside
        (`StageModel.beside`), that solve starts first, on the helper thread, and runs while
        completion and encoder do."""
        beside = self._start_classical(frame.solver, frame.stamp)
        enc = self.encode_prepared(frame)
        if on_encoded is not None:
            on_encoded()
        return self._pose_step(enc, beside)

    def step_encoded(self, enc: dict[str, np.ndarray], times: dict[str, float]) -> np.ndarray:
        """`step` on a frame a pipeline's reader thread has prepared and encoded (`encode_timed`)."""
        self.last_timing = FrameTiming(dict(times))
        return self._pose_step(enc)

    def _start_classical(self, solver: SolverFrame | None, stamp: float | None = None) -> Future | None:
        """Where the model solves the classical mode beside: the pair's inputs (the first pair's
        start from the cold start's solves too) and its classical solve (the `classical` stage),
        started on the helper thread, as a future of (inputs with `CLASSICAL_INPUT`, ms); None
        where not, or for the first frame."""
        if not self.model.beside or self._prev is None or solver is None:
            return None

        def solve() -> tuple[dict[str, np.ndarray], float]:
            t0 = time.perf_counter()
            inputs = self._pair_inputs(solver, stamp)
            inputs[CLASSICAL_INPUT] = self.model.solve_classical(inputs)
            return inputs, (time.perf_counter() - t0) * 1000

        return self._helper.submit(solve)

    def _pose_step(self, enc: dict[str, np.ndarray], beside: Future | None = None) -> np.ndarray:
        """The flow+pose half of a step: the pair (previous frame, `enc`), then `enc` is the previous.
        `beside`: the pair's inputs and classical solve, started by `_start_classical`."""
        t0 = time.perf_counter()
        if self._prev is not None:
            out = self._flow_pose(enc, beside)
            if self.keep_outputs:
                self.last["flowpose"] = out
            A2 = out["matrix"][0].astype(np.float64)
            if not np.all(np.isfinite(A2)):
                raise FloatingPointError(f"the network returned a non-finite pose at frame {self.frames}")
            if self.hold:  # the weighted pose on the `hold` pairs after one whose graph kept it
                A2, self.hold_left = held_pose(out, self.hold_left, self.hold)
            A2, held = self._guarded(A2, enc.get("stamp"))
            self.relative = change_frame(A2, self.calib.T_cam0_cam2)
            before, self.pose = self.pose, self.pose @ self.relative
            # from the poses, exactly as `prime` does on a resumed run (which reads them back), so
            # that an interrupted and resumed run starts every pair where an uninterrupted one does
            self.motion2 = self._motion_between(before, self.pose)
            start = out.get("start_next")
            if not held and start is not None and np.all(np.isfinite(start)):
                self.motion2 = start[0].astype(np.float64)
            classical = out.get(CLASSICAL_NEXT_OUTPUT)
            if held:  # both solves of the next pair start from the motion kept
                self.motion2_classical = None if classical is None else self.motion2
            elif classical is not None and np.all(np.isfinite(classical)):
                self.motion2_classical = classical[0].astype(np.float64)
            self.cold = False
        self.last_timing.ms["flowpose"] = (time.perf_counter() - t0) * 1000
        self._prev = enc
        self.frames += 1
        return self.pose.copy()

    @property
    def _prev_stamp(self) -> float | None:
        """Frame t-1's time in seconds, where it was given."""
        return None if self._prev is None else self._prev.get("stamp")

    def _guarded(self, A2: np.ndarray, stamp: float | None) -> tuple[np.ndarray, bool]:
        """The pair's image_2 motion A2 through the motion guard (`motion_guard`): the previous kept
        motion where A2's speed is physically out of reach of it; whether it was replaced."""
        dt = self.guard.interval(self._prev_stamp, stamp)
        A2, held = guard_motion(A2, dt, self.kept2, self.kept_dt, self.guard)
        self.kept2, self.kept_dt = A2, dt
        self.guarded += held
        return A2, held

    def _flow_pose(self, enc: dict, beside: Future | None = None) -> dict[str, np.ndarray]:
        """The flow+pose stage on (previous frame, `enc`); with the classical mode solved beside,
        that solve's pose as an input (solved here where no `beside` started it)."""
        if not self.model.geometric:
            return self.model.flow_pose(self._prev, enc, None)
        if beside is None:  # with the classical mode solved beside, `flow_pose` solves it first
            inputs = self._pair_inputs(enc.get("solver_frame"), enc.get("stamp"))
        else:
            inputs, self.last_timing.beside[BESIDE_STAGE] = beside.result()
        return self.model.flow_pose(self._prev, enc, inputs)

    def _pair_inputs(self, solver: SolverFrame | None, stamp: float | None = None) -> dict[str, np.ndarray]:
        """The pair's camera and solver inputs (frame t's solver frame `solver`), from `motion2`;
        the first pair of a point-solver graph, which has no previous motion, from the classical
        tracker's solve from `cold_start`'s guesses (`direct.first_motion`). Where the graph
        `chains_classical`, the classical solve's start too, from the previous classical pose. Constant
        velocity over the pair's own time (`stamp` against the previous frame's): the last motion
        scaled by the ratio of the two pairs' times, so that a dropped frame's pair starts twice as
        far (frames `MotionGuard.period` apart where a stamp is missing)."""
        gap = self.guard.interval(self._prev_stamp, stamp) / self.kept_dt
        feeds, start = {}, scaled_motion(self.motion2, gap)
        if self.model.point_solver:
            prev = self._prev["solver_frame"]
            feeds = solver_feeds(prev, solver, self.calib.K2, self.points.capacity)
            if self.cold and len(prev.points):
                start = cold_start_motion(prev, solver, self.calib.K2, self.model.config, self.cold_start)
            if self.chains_classical:
                classical = start if self.cold else scaled_motion(self._classical_start, gap)
                feeds[CLASSICAL_START_INPUT] = np.asarray(classical, np.float32).reshape(1, 4, 4)
        return {**camera_inputs(self.pre.K, start), **feeds}

    def prime(self, image: np.ndarray, points: np.ndarray | None, pose: np.ndarray,
              previous_pose: np.ndarray | None = None, start: np.ndarray | None = None,
              stamp: float | None = None, previous_stamp: float | None = None, hold_left: int = 0) -> None:
        """Resume: take frame t-1 and its known pose without estimating anything; with the pose
        before it, the next pair starts from that motion, as an uninterrupted run would (or from
        `start`, the saved `start_state`, where the graph `keeps_own_start`), and the motion guard
        compares the next pair with it (the two frames' stamps give its time). `hold_left`: the
        saved `hold_left` where the model holds its choice (`pt_select_hold`)."""
        if isinstance(hold_left, bool) or not (isinstance(hold_left, (int, np.integer)) and 0 <= hold_left <= self.hold):
            raise D3LVOInputError(None, f"prime's hold_left must be a whole number in 0..{self.hold} (pt_select_hold), "
                                        f"not {hold_left!r}")
        stamp, previous_stamp = as_stamp(stamp, "prime's stamp"), as_stamp(previous_stamp, "prime's previous_stamp")
        pose = rigid_pose(pose, "prime's pose")
        previous_pose = None if previous_pose is None else rigid_pose(previous_pose, "prime's previous_pose")
        if start is not None:  # one 4x4, or `start_state`'s (K,4,4)
            start = np.stack([rigid_pose(S, "prime's start") for S in (start if np.ndim(start) == 3 else [start])])
        self._prev = self.encode(image, points, stamp)
        self.pose = pose
        # no motion to start from or guard against unless the pose before (or the saved start) is given
        self.kept2, self.cold, self.motion2, self.relative = None, True, np.eye(4), np.eye(4)
        if previous_pose is not None:
            self.relative = relative(previous_pose, self.pose)
            self.motion2 = self._motion_between(previous_pose, self.pose)
            self.kept2 = self.motion2.copy()
            self.kept_dt = self.guard.interval(previous_stamp, stamp)
            self.cold = False
        if start is not None:
            self.motion2 = start[0]
        # without a saved classical start, the classical solve starts where the weighted one does
        self.motion2_classical = start[1] if start is not None and len(start) > 1 else None
        self.hold_left = int(hold_left)
        self.frames += 1

    def _motion_between(self, before: np.ndarray, after: np.ndarray) -> np.ndarray:
        """The image_2 motion between two cam0 poses: the Gauss-Newton head's next start."""
        return change_frame(relative(before, after), self.calib.T_cam2_cam0)


def cold_start_motion(prev: SolverFrame, cur: SolverFrame, K: np.ndarray, model_config: dict,
                      cold_start: ColdStartConfig) -> np.ndarray:
    """Where a point-solver model starts a pair with no previous motion: its classical mode's
    solve from the cold start's guesses (image_2, frame t in frame t-1); rest where it is off."""
    if not cold_start.enabled:
        return np.eye(4)
    from .direct import DirectConfig, TrackedFrame, first_motion

    cfg = replace(DirectConfig.of_model(model_config), cold_start=cold_start)
    return first_motion(TrackedFrame.of(prev.grey, prev.points, K, cfg.levels),
                        TrackedFrame.of(cur.grey, cur.points, K, cfg.levels, cur.depth), cfg)
