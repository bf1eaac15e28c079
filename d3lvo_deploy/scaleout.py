"""Many sequences, many workers: sequences split into overlapping chunks, run in parallel, stitched.

A chunk is a run of its own: its first pair starts the Gauss-Newton pose head from rest, where
the uninterrupted run starts it from the previous pair's motion (constant velocity). So chunks
overlap by `overlap` frames (default 2) and each is mapped onto the previous one through the
pose of their *last* shared frame: the cold-started pair lies inside the overlap and is dropped,
and the rest of the overlap is a check (reported as `overlap_residual_m`: what a cold start
moved the pose by). With the paper's MLP head (no start pose) the stitched trajectory equals the
sequential run exactly. Engines: `sequential`, `local` (a process pool on this machine) and
`ray` (Ray actors; a cluster via `address`); they run the same chunks, so their trajectories
are identical. Each worker holds one set of ONNX sessions for its life. Each sequence's
trajectory is written as soon as its last chunk is back.
"""

from __future__ import annotations

import os
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .errors import D3LVOInputError
from .geometry import se3_inv
from .motion_guard import MotionGuard
from .odometry import Odometry
from .onnx_model import SessionConfig, StageModel
from .pipeline import check_recording_fit, format_kitti
from .sequence import KittiSequence

ENGINES = ("sequential", "local", "ray")


@dataclass(frozen=True)
class Chunk:
    seq: str  # sequence name (output file stem)
    seq_dir: str
    start: int
    end: int  # exclusive
    guard: MotionGuard = MotionGuard()


def plan_chunks(n_frames: int, chunk: int, overlap: int) -> list[tuple[int, int]]:
    """Frame ranges of `chunk` frames sharing `overlap` frames with the previous range."""
    if overlap < 1 or chunk <= overlap:
        raise D3LVOInputError(None, f"need chunk > overlap >= 1 (got chunk {chunk}, overlap {overlap})")
    ranges, start = [], 0
    while True:
        end = min(start + chunk, n_frames)
        ranges.append((start, end))
        if end == n_frames:
            return ranges
        start = end - overlap


def stitch(parts: list[tuple[int, np.ndarray]]) -> tuple[np.ndarray, float]:
    """[(start, poses relative to that start)] in order -> one trajectory, and the overlap residual."""
    start0, first = parts[0]
    traj = {start0 + k: p for k, p in enumerate(first)}
    residual = 0.0
    for start, poses in parts[1:]:
        last = max(start + k for k in range(len(poses)) if start + k in traj)  # last shared frame
        anchor = traj[last] @ se3_inv(poses[last - start])
        for k, p in enumerate(poses):
            g = anchor @ p
            if start + k in traj:
                residual = max(residual, float(np.linalg.norm(traj[start + k][:3, 3] - g[:3, 3])))
            else:
                traj[start + k] = g
    return np.stack([traj[i] for i in sorted(traj)]), residual


# -- the work each worker does --------------------------------------------------------------------
_MODELS: dict[str, StageModel] = {}


def _model(model_dir: str, sc: SessionConfig) -> StageModel:
    if model_dir not in _MODELS:  # one session set per worker process, reused for every chunk
        _MODELS[model_dir] = StageModel(model_dir, sc)
    return _MODELS[model_dir]


def run_chunk(c: Chunk, model_dir: str, sc: SessionConfig) -> tuple[Chunk, np.ndarray]:
    seq = KittiSequence.open(c.seq_dir)
    odo = Odometry(model_dir, seq.calib, sc, model=_model(model_dir, sc), guard=c.guard)
    odo.fit_checked = True  # `run_many` checked each sequence's first frame before fanning out
    need_scan = odo.model.depth_input != "none"
    poses = []
    for i in range(c.start, c.end):
        odo.scan_source = f"{c.seq} frame {seq.frame_names[i]}'s scan"  # what a scan warning names
        poses.append(odo.step(seq.image(i), seq.scan(i) if need_scan else None, float(seq.times[i])))
    return c, np.stack(poses)


# -- engines ----------------------------------------------------------------------------------------
def _sequential(chunks, model_dir, sc, workers, address) -> Iterator[tuple[Chunk, np.ndarray]]:
    for c in chunks:
        yield run_chunk(c, model_dir, sc)


def _local(chunks, model_dir, sc, workers, address) -> Iterator[tuple[Chunk, np.ndarray]]:
    import multiprocessing as mp

    # spawn, not fork: onnxruntime's thread pools do not survive a fork of an initialised parent.
    # Each worker's OpenMP/BLAS/OpenCV pools get its share of the cores (as Ray does for its
    # workers); left at their default they oversubscribe the machine.
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: str(sc.threads) for k in _THREAD_VARS})
    try:
        with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                                 initializer=_limit_threads, initargs=(sc.threads,)) as pool:
            pending = {pool.submit(run_chunk, c, model_dir, sc) for c in chunks}
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    yield f.result()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _limit_threads(n: int) -> None:
    import cv2

    cv2.setNumThreads(n)


def _ray(chunks, model_dir, sc, workers, address) -> Iterator[tuple[Chunk, np.ndarray]]:
    try:
        import ray
        from ray.util import ActorPool
    except ImportError:
        raise D3LVOInputError(None, "--engine ray needs Ray: pip install 'd3lvo-deploy[ray]'") from None
    started = not ray.is_initialized()
    if started:
        kw = {"address": address} if address else {"num_cpus": workers, "include_dashboard": False}
        ray.init(**kw, log_to_driver=False, configure_logging=False)

    @ray.remote(num_cpus=1)
    class Worker:
        def run(self, c, model_dir, sc):
            return run_chunk(c, model_dir, sc)

    try:
        pool = ActorPool([Worker.remote() for _ in range(workers)])
        for c in chunks:
            pool.submit(lambda a, ch: a.run.remote(ch, model_dir, sc), c)
        while pool.has_next():
            try:
                result = pool.get_next_unordered()
            except ray.exceptions.RayTaskError as e:
                # a worker's bad-input error (a truncated scan) is the one line it would be on one
                # machine, not Ray's wrapped traceback
                cause = getattr(e, "cause", None)
                if isinstance(cause, D3LVOInputError):
                    raise D3LVOInputError(cause.path, cause.problem) from None
                raise
            yield result
    finally:
        if started:
            ray.shutdown()


def check_engine(engine: str, workers: int) -> None:
    """--engine and --workers, before anything (a progress bar) starts."""
    if engine not in ENGINES:
        raise D3LVOInputError(None, f"--engine must be one of {', '.join(ENGINES)}, not {engine!r}")
    if workers < 1:
        raise D3LVOInputError(None, "--workers must be at least 1")


def run_many(seq_dirs: dict[str, Path], model_dir: str | Path, out_dir: Path, engine: str = "local", workers: int = 2,
             chunk: int = 1000, overlap: int = 2, address: str | None = None, sc: SessionConfig | None = None,
             on_chunk: Callable[[Chunk], None] | None = None,
             on_sequence: Callable[[str, Path, float], None] | None = None,
             guard: MotionGuard = MotionGuard()) -> dict[str, float]:
    """Run every sequence; returns {sequence: overlap residual (m)}. Trajectories go to out_dir/NAME.txt."""
    check_engine(engine, workers)
    model_dir = str(Path(model_dir).resolve())
    StageModel(model_dir)  # verify the model once, here, before fanning out
    sc = sc or SessionConfig()
    if not sc.threads:  # OMP_NUM_THREADS each where set, else the machine's cores split between the workers
        sc = replace(sc, threads=sc.engine_threads or max(1, (os.cpu_count() or 1) // workers))
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise D3LVOInputError(out_dir, f"cannot create the output folder ({e.strerror})") from None
    chunks, expected = [], {}
    for name, d in seq_dirs.items():
        seq = KittiSequence.open(d)
        check_recording_fit(seq, 0, f"{name}/{seq.frame_names[0]}")  # once per sequence, not per chunk
        ranges = plan_chunks(len(seq), chunk, overlap)
        expected[name] = len(ranges)
        chunks += [Chunk(name, str(d), s, e, guard) for s, e in ranges]
    got: dict[str, list[tuple[int, np.ndarray]]] = {n: [] for n in seq_dirs}
    residuals = {}
    engine_fn = {"sequential": _sequential, "local": _local, "ray": _ray}[engine]
    for c, poses in engine_fn(chunks, model_dir, sc, workers, address):
        got[c.seq].append((c.start, poses))
        if on_chunk is not None:
            on_chunk(c)
        if len(got[c.seq]) == expected[c.seq]:
            traj, res = stitch(sorted(got[c.seq], key=lambda x: x[0]))
            path = out_dir / f"{c.seq}.txt"
            tmp = path.with_name(path.name + ".part")
            tmp.write_text("".join(format_kitti(T) + "\n" for T in traj))
            tmp.replace(path)
            residuals[c.seq] = res
            if on_sequence is not None:
                on_sequence(c.seq, path, res)
    return residuals


def parse_sequences(spec: str) -> list[str]:
    """'00-10' or '00,02,05' or '09' -> zero-padded ids."""
    out: list[str] = []
    try:
        for part in spec.split(","):
            if "-" in part:
                a, b = part.split("-")
                if int(b) < int(a):
                    raise D3LVOInputError(None, f"--sequences {spec!r}: the range {part.strip()} runs backwards "
                                                f"(write {b.strip()}-{a.strip()})")
                out += [f"{i:02d}" for i in range(int(a), int(b) + 1)]
            elif part.strip():
                out.append(f"{int(part):02d}")
    except ValueError:
        raise D3LVOInputError(None, f"--sequences must look like 00-10 or 00,02,05, not {spec!r}") from None
    if not out:
        raise D3LVOInputError(None, f"--sequences {spec!r} names no sequence")
    return out
