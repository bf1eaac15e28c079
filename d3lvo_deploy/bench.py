"""Per-stage latency of the ONNX pipeline on real-format frames (torch-free part of `d3lvo bench`)."""

from __future__ import annotations

import resource
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .odometry import BESIDE_ROW, Odometry
from .onnx_model import SessionConfig, StageModel
from .pipeline import engine_depth
from .sequence import KittiSequence

# BESIDE_ROW, a stage that runs on another thread beside the others (`FrameTiming.beside`): timed,
# but not part of the frame's total, which is its wall time
BENCH_STAGES = ("project", "completion", "encoder", BESIDE_ROW, "flowpose", "total")
TURN_FRAMES = 5  # frames a stream runs before the next one's turn (`take_turns`)
ENGINE_WARMUP = 3  # untimed frames per engine first (`warm_up`): first-call allocations, caches


@dataclass
class StageTimes:
    samples: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in BENCH_STAGES})
    pipelined_fps: float | None = None  # frames/s of wall time with the two-deep pipeline

    def add(self, ms: dict[str, float]) -> None:
        for k, v in ms.items():
            self.samples.setdefault(k, []).append(v)
        self.samples["total"].append(sum(v for k, v in ms.items() if k not in ("total", BESIDE_ROW)))

    def summary(self) -> dict[str, dict[str, float]]:
        out = {}
        for k, v in self.samples.items():
            if v:
                a = np.asarray(v)
                # max: a 10 Hz sensor needs every frame in budget, not the typical one
                out[k] = {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)), "min": float(a.min()),
                          "max": float(a.max())}
        return out


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports KiB


def bench_onnx(model_dir, seq: KittiSequence, sc: SessionConfig, runs: int,
               warmup: int = ENGINE_WARMUP) -> StageTimes:
    """Steady-state per-frame latency: the stream runs over the sequence's frames (cycled), as on a car."""
    return bench_engines(model_dir, seq, [sc], runs, warmup)[0]


def bench_frames(seq: KittiSequence) -> list[tuple[np.ndarray, np.ndarray]]:
    """The frames every timed stream cycles through (image, scan), read once."""
    return [(seq.image(i), seq.scan(i)) for i in range(min(len(seq), 10))]


class EngineStream:
    """One engine's stream over the frames: each call steps the next frame and returns its stage times."""

    def __init__(self, model_dir, seq: KittiSequence, sc: SessionConfig, frames: list):
        self.sc, self.frames, self.k = sc, frames, 0
        self.model = StageModel(model_dir, sc)
        self.odo = Odometry(model_dir, seq.calib, sc, model=self.model)

    def __call__(self) -> dict[str, float]:
        self.odo.step(*self.frames[self.k % len(self.frames)])
        self.k += 1
        return self.odo.last_timing.rows

    def finish(self, times: StageTimes, runs: int) -> None:
        """Ends profiling, or else times the same stream pipelined (`pipelined_fps`), with the
        flow+pose stage's threads as a pipelined run has them."""
        if self.sc.profile_dir:
            self.model.end_profiling()
        else:
            depth = engine_depth(self.model.backend, self.sc.pipelined(3) != self.sc)  # as a run decides
            changed = self.model.open_for(self.sc.pipelined(depth))  # a pipelined run's threads and stages
            if changed:
                warm_up([self], ENGINE_WARMUP)
            times.pipelined_fps = pipelined_fps(self.odo, self.frames, runs, depth)


def warm_up(streams: list[Callable[[], dict]], frames: int) -> None:
    """Steps each stream `frames` times untimed: first-call allocations, caches, compiles."""
    for stream in streams:
        for _ in range(frames):
            stream()


def take_turns(streams: list[Callable[[], dict]], runs: int, block: int = TURN_FRAMES) -> list[StageTimes]:
    """`runs` timed frames of each stream, taking turns `block` frames at a time: a VM's speed drifts
    by tens of percent within minutes, and streams timed one after the other would each be timed in
    a different phase of it; taking turns, their ratio is measured under the same drift. Each
    stream steps its own run of the frames, so every one sees consecutive pairs."""
    times = [StageTimes() for _ in streams]
    while min(len(t.samples["total"]) for t in times) < runs:
        for stream, t in zip(streams, times):
            for _ in range(min(block, runs - len(t.samples["total"]))):
                t.add(stream())
    return times


def bench_engines(model_dir, seq: KittiSequence, scs: list[SessionConfig], runs: int, warmup: int = ENGINE_WARMUP,
                  block: int = TURN_FRAMES) -> list[StageTimes]:
    """`bench_onnx` for several engines at once, taking turns (`take_turns`) after each is warmed up."""
    frames = bench_frames(seq)
    streams = [EngineStream(model_dir, seq, sc, frames) for sc in scs]
    warm_up(streams, warmup)
    times = take_turns(streams, runs, block)
    for stream, t in zip(streams, times):
        stream.finish(t, runs)
    return times


def pipelined_fps(odo: Odometry, frames: list, runs: int, depth: int = 2) -> float:
    """Throughput as `d3lvo run --pipeline` streams: frame t+1 prepared (projection, IP-Basic,
    solver points) on a second thread while the network works on frame t, and with `depth` 3 also
    completed and encoded there, beside frame t's flow+pose stage (`pipeline.pipeline_depth`).
    Latency per frame is what the stage times add up to; this is how many frames per second pass."""
    def ahead_of(k: int):
        frame = odo.prepare(*frames[k % len(frames)], threads=1)  # one core beside the network, as a run's reader
        return odo.encode_timed(frame) if depth == 3 else frame

    with ThreadPoolExecutor(1) as pool:
        ahead = pool.submit(ahead_of, 0)
        t0 = time.perf_counter()
        for k in range(runs):
            item = ahead.result()
            if depth == 3:
                ahead = pool.submit(ahead_of, k + 1)
                odo.step_encoded(*item)
                continue

            def read_next(k=k):
                nonlocal ahead
                ahead = pool.submit(ahead_of, k + 1)

            odo.step_prepared(item, on_encoded=read_next)
        wall = time.perf_counter() - t0
        ahead.result()
    return runs / wall


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1000


def profile_summary(profile_files: list[str], top: int = 8) -> dict[str, list[tuple[str, float]]]:
    """Per stage, the op types that took the most time (ms summed over the profiled runs); a file
    that is not an onnxruntime profile (a list of trace events) is left out."""
    import json
    from collections import defaultdict

    out = {}
    for f in profile_files:
        try:
            events = json.loads(Path(f).read_text())
        except (OSError, ValueError):
            continue
        if not isinstance(events, list):
            continue
        by_op: dict[str, float] = defaultdict(float)
        for e in events:
            if not isinstance(e, dict):
                continue
            if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
                by_op[e.get("args", {}).get("op_name", "?")] += e.get("dur", 0) / 1000.0
        stage = f.rsplit("/", 1)[-1].split("_", 1)[0]
        out[stage] = sorted(by_op.items(), key=lambda kv: -kv[1])[:top]
    return out
