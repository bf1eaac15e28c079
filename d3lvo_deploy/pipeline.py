"""Run odometry over a recording (any input format) and write the trajectory as it goes.

Each pose line is appended and flushed as soon as it is computed, so an interrupted run keeps
its finished frames; `resume=True` re-reads them, re-encodes the last written frame and carries
on, giving the same file an uninterrupted run would (poses are written with 17 significant
digits, which read back to the same float64).
"""

from __future__ import annotations

import numbers
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, closing
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from .calib import check_fit
from .errors import D3LVOInputError
from .motion_guard import MotionGuard
from .odometry import STAGES, FrameSizeError, Odometry
from .onnx_model import SessionConfig, StageModel
from .poses import format_kitti_line, format_tum_line, read_poses
from .datasets import Recording
from .viz import network_view


EXACT = ".17g"  # 17 significant digits read back to the same float64: what makes --resume exact


def format_kitti(T: np.ndarray) -> str:
    return format_kitti_line(T, EXACT)


def format_tum(T: np.ndarray, stamp: float) -> str:
    return format_tum_line(T, stamp, EXACT)


@dataclass
class RunSummary:
    frames: int
    out: Path
    resumed_from: int = 0
    latencies_ms: dict[str, list[float]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    wall_s: float = 0.0  # from the first frame read to the last pose written
    pipelined: bool = False
    deep: bool = False  # pipelined three deep: the next frame also completed and encoded ahead
    guarded: int = 0  # pairs of this run where the motion guard kept the previous motion

    @property
    def throughput(self) -> float:
        """Frames per second of wall time: with the pipeline, more than 1000 / per-frame latency."""
        done = self.frames - self.resumed_from
        return done / self.wall_s if self.wall_s > 0 else float("nan")

    def stats(self) -> dict[str, dict[str, float]]:
        out = {}
        for k, v in self.latencies_ms.items():
            if v:
                a = np.asarray(v)
                out[k] = {"mean": float(a.mean()), "p90": float(np.percentile(a, 90)), "max": float(a.max())}
        return out


@dataclass
class RunConfig:
    out: Path
    fmt: str = "kitti"
    start: int = 0
    end: int | None = None
    resume: bool = False
    overwrite: bool = False  # replace a trajectory file that already holds poses
    realtime: bool = False  # pace frames by times.txt, like a live sensor
    viz_dir: Path | None = None  # write a picture of what the network sees every `viz_every` frames
    viz_every: int = 10  # also the frames whose images go into the Rerun recording
    rerun_path: Path | None = None  # write a Rerun recording (.rrd) of the run
    # read and prepare frame t+1 (image, scan, projection, IP-Basic, solver points; on
    # onnxruntime also completion and encoder: `pipeline_depth`) on a second thread while the
    # network works on frame t, the flow+pose stage then one thread short (`SessionConfig.pipelined`);
    # the poses are the same either way. More frames per second (on 2 cores a fifth more on
    # OpenVINO, two fifths on onnxruntime), each frame's latency a little longer
    # (docs/performance.md): off by default, the switch for a CPU that falls behind
    pipeline: bool = False
    # a solved motion whose speed is out of a car's reach of the last one's is replaced by the last
    # (`motion_guard`; off by default); a tracker given to the run brings its own
    guard: MotionGuard = field(default_factory=MotionGuard)


def _existing_poses(path: Path, fmt: str, n_max: int) -> np.ndarray:
    if not path.is_file() or path.stat().st_size == 0:
        return np.zeros((0, 4, 4))
    text = path.read_text()
    if not text.endswith("\n"):  # a line cut by the interruption: drop it
        text = text[: text.rfind("\n") + 1]
        path.write_text(text)
    if not text:
        return np.zeros((0, 4, 4))
    traj = read_poses(path, fmt="kitti" if fmt == "kitti" else "tum")
    if len(traj) > n_max:
        raise D3LVOInputError(path, f"holds {len(traj)} poses, more than the {n_max} frames of this run")
    return traj.poses


def start_file(out: Path) -> Path:
    """Where a run whose graph keeps its own start (`Odometry.keeps_own_start`) saves, per frame,
    the next pair's start (and, where the model holds its choice, `Odometry.hold_left` after the
    matrices), so that --resume continues exactly where the run stopped."""
    return out.with_name(out.name + ".start")


def _saved_starts(path: Path, count: int, per_line: int = 1,
                  holds: bool = False) -> tuple[np.ndarray, np.ndarray | None] | None:
    """The first `count` lines of starts saved in `path`: ((count, per_line, 4, 4), each line's
    `Odometry.start_state`; with `holds`, (count,) each line's `Odometry.hold_left`, else None),
    the file rewritten to hold just those; None where fewer were saved or they cannot be read."""
    try:
        rows = [r.split() for r in path.read_text().splitlines()]
        rows = [r for r in rows if len(r) == 12 * per_line + holds]
        if len(rows) < count:
            return None
        T = np.tile(np.eye(4), (count, per_line, 1, 1))
        matrices = np.array([r[:12 * per_line] for r in rows[:count]], dtype=np.float64)
        T[:, :, :3, :] = matrices.reshape(count, per_line, 3, 4)
        left = np.array([int(r[-1]) for r in rows[:count]]) if holds else None
        if left is not None and (left < 0).any():
            return None
        path.write_text("".join(" ".join(r) + "\n" for r in rows[:count]))
    except (OSError, ValueError):  # UnicodeDecodeError is a ValueError
        return None
    return T, left


def _start_line(state: np.ndarray, hold_left: int | None = None) -> str:
    """One line of the start file: `Odometry.start_state`'s matrices, 12 numbers each, then
    `Odometry.hold_left` where the model holds its choice (`_hold_left`)."""
    return " ".join(format_kitti(T) for T in state) + ("" if hold_left is None else f" {hold_left}") + "\n"


def _hold_left(odo) -> int | None:
    """The tracker's count of pairs left to hold (`pt_select_hold`), None where it holds nothing."""
    return odo.hold_left if getattr(odo, "hold", 0) else None


def _open_starts(odo, out: Path, done: int, stack: ExitStack):
    """(the file each frame's start is appended to, the saved starts a resumed run begins from)
    where the tracker keeps its own start; else (None, None), and any start file beside `out`
    removed: it cannot belong to poses this tracker writes."""
    path = start_file(out)
    if not getattr(odo, "keeps_own_start", False):
        try:
            path.unlink(missing_ok=True)
        except OSError:
            pass
        return None, None
    saved = _saved_starts(path, done, len(odo.start_state()), _hold_left(odo) is not None) if done else None
    if done > 1 and saved is None:
        warnings.warn(f"{path}: the solver's saved starts are missing or short, so the resumed run starts from "
                      "the last poses' motion and may differ slightly from an uninterrupted run")
    try:
        fh = stack.enter_context(open(path, "a" if saved is not None else "w", buffering=1))
    except OSError as e:
        raise D3LVOInputError(path, f"cannot write the solver's starts ({e.strerror})") from None
    return fh, saved


def _write_viz(path: Path, view: dict) -> None:
    """One panel of what the network saw for this frame (d3lvo_deploy.viz)."""
    from .viz import frame_panel, write_panel

    panel = frame_panel(view["image"], view["lidar_m"], view["dense_m"], view["flow"], view["confidence"],
                        points_head=view["points_head"])
    try:
        write_panel(path, panel)
    except OSError as e:
        raise D3LVOInputError(path, f"cannot write the picture ({e})") from None


@dataclass
class RunPlan:
    """A checked run: arguments valid, model loaded, poses already written read back."""
    seq: Recording
    rc: RunConfig
    odo: object
    out: Path
    n: int
    done: np.ndarray
    depth: int = 1  # frames in flight: 1 one at a time, 2 or 3 pipelined (`pipeline_depth`)
    sc: SessionConfig | None = None  # the network's sessions as opened (None: not the network)

    @property
    def finished(self) -> bool:
        return len(self.done) == self.n


def check_recording_fit(seq: Recording, i: int, label: str | None = None) -> None:
    """The recording's calibration against frame i's image and scan (`calib.check_fit`), before
    any work: the trackers then skip their own first-frame check (`fit_checked`)."""
    image = seq.image(i)
    scan_file = seq.scan_path(i) if hasattr(seq, "scan_path") else seq.root  # a file per scan, or the recording
    check_fit(seq.calib, image.shape[1], image.shape[0], seq.scan(i), getattr(seq, "calib_path", None) or seq.root,
              label or seq.frame_names[i], scan_file)


def prepare_run(seq: Recording, model_dir: str | Path | None, rc: RunConfig, sc: SessionConfig = SessionConfig(),
                model: StageModel | None = None, odometry=None) -> RunPlan:
    """Every check that can fail before the first frame (range, format, output file, model), so
    a bad argument is one error before any work or progress bar."""
    end = len(seq) if rc.end is None else rc.end
    if not 0 <= rc.start < end <= len(seq):
        raise D3LVOInputError(seq.root, f"frame range {rc.start}..{end} is outside 0..{len(seq)}")
    fmt = rc.fmt.lower()
    if fmt not in ("kitti", "tum"):
        raise D3LVOInputError(None, f"--pose-format must be kitti or tum, not {rc.fmt!r}")
    # paths as strings (the API's callers), and the picture interval, as the CLI gives them
    as_path = lambda p: None if p is None else Path(p)  # noqa: E731
    rc = replace(rc, fmt=fmt, end=end, out=Path(rc.out), viz_dir=as_path(rc.viz_dir), rerun_path=as_path(rc.rerun_path))
    whole = isinstance(rc.viz_every, numbers.Integral) and not isinstance(rc.viz_every, bool)
    if (rc.viz_dir is not None or rc.rerun_path is not None) and not (whole and rc.viz_every >= 1):
        raise D3LVOInputError(None, f"viz_every must be a whole number of frames, 1 or more, not {rc.viz_every!r}")
    if rc.viz_dir is not None and odometry is not None and not hasattr(odometry, "model"):
        raise D3LVOInputError(rc.viz_dir, "--viz shows the network's inputs and outputs; the direct tracker has none")
    if model_dir is None and model is None and odometry is None:  # the API's default, as the CLI's
        from .bundled import bundled_model_dir

        model_dir = bundled_model_dir()
    if rc.rerun_path is not None:
        from .extras import require

        require("rerun", what="--rerun")
        if Path(rc.rerun_path).is_dir():
            raise D3LVOInputError(rc.rerun_path, "is a folder; --rerun names the recording to write (e.g. run.rrd)")
        if Path(rc.rerun_path).is_file() and rc.resume:  # the interrupted run's recording stays as it is
            rc = replace(rc, rerun_path=_unused(Path(rc.rerun_path), "resumed"))
        elif Path(rc.rerun_path).is_file() and not rc.overwrite:
            raise D3LVOInputError(rc.rerun_path, "already holds a Rerun recording; --overwrite replaces it, or name "
                                                 "another file")
    out = Path(rc.out)
    if out.is_dir():
        raise D3LVOInputError(out, "is a folder; --out names the trajectory file to write (e.g. 09.txt)")
    if not rc.resume and not rc.overwrite and out.is_file() and out.stat().st_size > 0:
        held = out.read_text().count("\n")
        raise D3LVOInputError(out, f"already holds {held} poses from an earlier run; --resume continues it, "
                                   "--overwrite starts over")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise D3LVOInputError(out.parent, f"cannot create the output folder ({e.strerror})") from None
    if rc.rerun_path is not None:
        from .results import make_output_folder

        make_output_folder(Path(rc.rerun_path).parent, "--rerun", "the recording")
    if rc.viz_dir is not None and rc.viz_dir.exists() and not rc.viz_dir.is_dir():  # else found at the first picture
        raise D3LVOInputError(rc.viz_dir, "is a file; --viz names the folder for the pictures")
    n = end - rc.start
    if rc.viz_dir is not None and n <= rc.viz_every:  # the pictures are of frames viz_every, 2 viz_every, ...
        warnings.warn(f"{rc.viz_dir}: --viz draws frames {rc.viz_every}, {2 * rc.viz_every}, ... of a run (--viz-every "
                      f"{rc.viz_every}), and this one has {n} frames: no picture (a smaller --viz-every draws more)")
    check_recording_fit(seq, rc.start)
    done = _existing_poses(out, rc.fmt, n) if rc.resume else np.zeros((0, 4, 4))
    opens = odometry is None and model is None  # this run opens the network's sessions, split as it pipelines
    backend = model.backend if model is not None else sc.resolved().backend
    depth = pipeline_depth(rc, backend, n - len(done), prepares=odometry is None or hasattr(odometry, "prepare"),
                           splits=opens and sc.pipelined(3) != sc)
    if depth > 1 and opens:
        sc = sc.pipelined(depth)
    odo = odometry if odometry is not None else Odometry(model_dir, seq.calib, sc, model=model, guard=rc.guard)
    odo.fit_checked = True  # above, against the recording's own first frame and calibration file
    return RunPlan(seq=seq, rc=rc, odo=odo, out=out, n=n, done=done, depth=depth, sc=sc if opens else None)


def pipeline_depth(rc: RunConfig, backend: str, frames: int, prepares: bool = True, splits: bool = True) -> int:
    """How many frames a run has in flight. Pipelined (`rc.pipeline`, more than one frame to go, a
    tracker that prepares frames apart), a reader thread reads and prepares frame t+1 while the
    network works on frame t (2). On onnxruntime it also runs frame t+1's completion and encoder,
    on one thread beside frame t's flow+pose stage (3), which measured faster there and not on
    OpenVINO (docs/performance.md): where the run opens the sessions with that split (`splits`)
    and does not keep each frame's tensors for pictures (`--viz`, `--rerun`)."""
    if not rc.pipeline or frames < 2 or not prepares:
        return 1
    pictures = rc.viz_dir is not None or rc.rerun_path is not None
    return 2 if pictures else engine_depth(backend, splits)


def engine_depth(backend: str, splits: bool) -> int:
    """A pipeline's depth on an engine (`pipeline_depth`, the bench's pipelined rate): three where
    it measured faster, onnxruntime, and the sessions' threads can be split; else two."""
    return 3 if splits and backend == "onnxruntime" else 2


def _unused(path: Path, word: str) -> Path:
    """path's name with `-word` (then `-word-2`, ...) before its suffix: the first that is free."""
    k, candidate = 1, path.with_name(f"{path.stem}-{word}{path.suffix}")
    while candidate.exists():
        k += 1
        candidate = path.with_name(f"{path.stem}-{word}-{k}{path.suffix}")
    return candidate


def run_sequence(seq: Recording, model_dir: str | Path | None, rc: RunConfig, sc: SessionConfig = SessionConfig(),
                 progress: Callable[[int, int, float], None] | None = None, model: StageModel | None = None,
                 odometry=None) -> RunSummary:
    """Estimate poses for frames [start, end) and write them to rc.out; returns timings.
    `odometry`: another tracker with Odometry's interface (the direct reference tracker)."""
    return execute_run(prepare_run(seq, model_dir, rc, sc, model=model, odometry=odometry), progress)


def execute_run(plan: RunPlan, progress: Callable[[int, int, float], None] | None = None) -> RunSummary:
    seq, rc, odo, out, n, done = plan.seq, plan.rc, plan.odo, plan.out, plan.n, plan.done
    summary = RunSummary(frames=n, out=out, resumed_from=len(done))
    summary.latencies_ms = {k: [] for k in (*STAGES, "total")}
    if plan.finished:
        return summary
    mode = "a" if len(done) else "w"
    try:
        fh = open(out, mode, buffering=1)
    except OSError as e:
        raise D3LVOInputError(out, f"cannot write the trajectory ({e.strerror})") from None
    with ExitStack() as stack:
        stack.enter_context(fh)
        recorder = None
        if rc.rerun_path is not None:
            from .recording import RerunRecorder

            recorder = stack.enter_context(closing(RerunRecorder(Path(rc.rerun_path), seq.calib)))
        pictures = rc.viz_dir is not None or recorder is not None
        starts, saved = _open_starts(odo, out, len(done), stack)
        if len(done):
            k = rc.start + len(done) - 1
            extra = {} if saved is None else {"start": saved[0][-1]}
            if saved is not None and saved[1] is not None:
                extra["hold_left"] = int(min(saved[1][-1], odo.hold))
            odo.scan_source = f"frame {seq.frame_names[k]}'s scan"
            odo.prime(seq.image(k), seq.scan(k) if odo.needs_scan else None, done[-1],
                      done[-2] if len(done) >= 2 else None, **extra, stamp=float(seq.times[k]),
                      previous_stamp=float(seq.times[k - 1]) if len(done) >= 2 else None)
            if starts is not None and saved is None:  # the rows line up with the poses again, the last the start used
                state, left = odo.start_state(), _hold_left(odo)
                # identity starts (and no hold) on the rows the run cannot know
                rest = [(np.tile(np.eye(4), (len(state), 1, 1)), None if left is None else 0)] * (len(done) - 1)
                starts.write("".join(_start_line(*row) for row in [*rest, (state, left)]))
        t_wall0 = time.perf_counter()
        pipelined = plan.depth > 1
        deep = pipelined and plan.depth == 3  # the reader also completes and encodes the frame
        summary.pipelined, summary.deep = pipelined, deep

        def load(i: int):
            """Read frame i (and, pipelined, prepare it); a bad file says which poses are saved. With
            --realtime it waits for the frame's time first, on a reader thread reading ahead too, as
            from a live sensor."""
            if rc.realtime:
                wait = (seq.times[i] - seq.times[rc.start + len(done)]) - (time.perf_counter() - t_wall0)
                if wait > 0:
                    time.sleep(wait)
            t0 = time.perf_counter()
            # set before the frame's scan is checked, here or by `step` (in a pipeline the reader
            # prepares each frame after the first, which the main thread steps before reading ahead)
            odo.scan_source = f"frame {seq.frame_names[i]}'s scan"
            try:  # a bad file, or a frame unlike the others (its size)
                image = seq.image(i)
                points = seq.scan(i) if odo.needs_scan else None
                read_ms = (time.perf_counter() - t0) * 1000
                # one thread: this reader has one core beside the network
                prepared = (odo.prepare(image, points, threads=1, stamp=float(seq.times[i]))
                            if pipelined and odo.pre is not None else None)
            except D3LVOInputError as e:
                raise frame_error(e, i) from None
            encoded = odo.encode_timed(prepared) if deep and prepared is not None else None
            return image, points, prepared, encoded, read_ms

        def frame_error(e: D3LVOInputError, i: int) -> D3LVOInputError:
            """Frame i's error, naming its file (a frame of another size: its image, where the recording
            has a file per image) or else the frame, and the poses saved."""
            path = e.path
            if path is None and isinstance(e, FrameSizeError) and hasattr(seq, "image_path"):
                path = seq.image_path(i)
            problem = e.problem if path is not None else f"frame {seq.frame_names[i]}: {e.problem}"
            saved = (f"poses of frames {rc.start}..{i - 1} are saved in {out}, fix the frame and rerun with "
                     "--resume" if i > rc.start else "no pose is saved yet, fix the frame and rerun")
            return D3LVOInputError(path, f"{problem}; {saved}")

        pool = ThreadPoolExecutor(1, thread_name_prefix="d3lvo-read") if pipelined else None
        try:
            ahead = None
            for j in range(len(done), n):
                i = rc.start + j
                image, points, prepared, encoded, read_ms = ahead.result() if ahead is not None else load(i)
                ahead = None
                if pictures and hasattr(odo, "keep_outputs"):
                    odo.keep_outputs = j > 0 and (i - rc.start) % rc.viz_every == 0

                def read_next(i=i, j=j):
                    nonlocal ahead
                    if pool is not None and j + 1 < n:
                        ahead = pool.submit(load, i + 1)

                if encoded is not None:  # only the flow+pose stage left: the reader takes the next frame now
                    read_next()
                    pose = odo.step_encoded(*encoded)
                elif prepared is not None:
                    pose = odo.step_prepared(prepared, on_encoded=read_next)
                else:
                    try:
                        pose = odo.step(image, points, float(seq.times[i]))
                    except D3LVOInputError as e:  # a frame unlike the others (its size)
                        raise frame_error(e, i) from None
                    read_next()  # the first frame has fixed the view: from here on, prepared ahead
                view = None
                if getattr(odo, "keep_outputs", False):  # a chosen frame: what the network saw, once for both
                    view = network_view(odo.last, odo.model.dense_depth_m, "completion" in odo.model.sessions)
                if rc.viz_dir is not None and view is not None:
                    _write_viz(rc.viz_dir / f"{seq.frame_names[i]}.png", view)
                if recorder is not None:
                    recorder.frame(i, pose, points, view, None if view is None else odo.pre.K)
                line = format_kitti(pose) if rc.fmt == "kitti" else format_tum(pose, float(seq.times[i]))
                if starts is not None:  # before the pose: a run stopped between the two resumes exactly
                    starts.write(_start_line(odo.start_state(), _hold_left(odo)))
                fh.write(line + "\n")
                fh.flush()
                for k, v in odo.last_timing.rows.items():  # the time beside (another thread) not in the total
                    summary.latencies_ms.setdefault(k, []).append(v)
                summary.latencies_ms.setdefault("read", []).append(read_ms)
                summary.latencies_ms["total"].append(odo.last_timing.total + read_ms)
                summary.wall_s = time.perf_counter() - t_wall0
                if progress is not None:
                    progress(j + 1, n, odo.last_timing.total + read_ms)
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
    summary.guarded = getattr(odo, "guarded", 0)
    return summary

