"""Per-stage latency of the ONNX pipeline on real-format frames (torch-free part of `d3lvo bench`)."""

from __future__ import annotations

import resource
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .odometry import Odometry
from .onnx_model import SessionConfig, StageModel
from .sequence import KittiSequence

BENCH_STAGES = ("project", "completion", "encoder", "flowpose", "total")
TURN_FRAMES = 5  # frames an engine runs before the next engine's turn (`bench_engines`)


@dataclass
class StageTimes:
    samples: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in BENCH_STAGES})
    pipelined_fps: float | None = None  # frames/s of wall time with the two-deep pipeline

    def add(self, ms: dict[str, float]) -> None:
        for k, v in ms.items():
            self.samples.setdefault(k, []).append(v)
        self.samples["total"].append(sum(v for k, v in ms.items() if k != "total"))

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


def bench_onnx(model_dir, seq: KittiSequence, sc: SessionConfig, runs: int, warmup: int = 3) -> StageTimes:
    """Steady-state per-frame latency: the stream runs over the sequence's frames (cycled), as on a car."""
    return bench_engines(model_dir, seq, [sc], runs, warmup)[0]


def bench_engines(model_dir, seq: KittiSequence, scs: list[SessionConfig], runs: int, warmup: int = 3,
                  block: int = TURN_FRAMES) -> list[StageTimes]:
    """`bench_onnx` for several engines at once, taking turns `block` frames at a time: a VM's speed
    drifts by tens of percent within minutes, and engines timed one after the other would each be
    timed in a different phase of it; taking turns, their ratio is measured under the same drift.
    Each engine streams its own run of the frames, so every one sees consecutive pairs."""
    models = [StageModel(model_dir, sc) for sc in scs]
    odos = [Odometry(model_dir, seq.calib, sc, model=m) for sc, m in zip(scs, models)]
    frames = [(seq.image(i), seq.scan(i)) for i in range(min(len(seq), 10))]
    times = [StageTimes() for _ in scs]
    done = [0] * len(scs)  # frames stepped per engine, warm-up included
    while min(done) < warmup + runs:
        for e, odo in enumerate(odos):
            for _ in range(min(block, warmup + runs - done[e])):
                k = done[e]
                odo.step(*frames[k % len(frames)])
                if k >= warmup:
                    times[e].add(dict(odo.last_timing.ms))
                done[e] += 1
    for sc, model, odo, t in zip(scs, models, odos, times):
        if sc.profile_dir:
            model.end_profiling()
        else:
            t.pipelined_fps = pipelined_fps(odo, frames, runs)
    return times


def pipelined_fps(odo: Odometry, frames: list, runs: int) -> float:
    """Throughput as `d3lvo run` streams: frame t+1 prepared (projection, IP-Basic, solver points)
    on a second thread while the network works on frame t. Latency per frame is what the stage
    times add up to; this is how many frames per second pass."""
    with ThreadPoolExecutor(1) as pool:
        ahead = pool.submit(odo.prepare, *frames[0])
        t0 = time.perf_counter()
        for k in range(runs):
            prepared = ahead.result()

            def read_next(k=k):
                nonlocal ahead
                ahead = pool.submit(odo.prepare, *frames[(k + 1) % len(frames)])

            odo.step_prepared(prepared, on_encoded=read_next)
        wall = time.perf_counter() - t0
        ahead.result()
    return runs / wall


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1000


def profile_summary(profile_files: list[str], top: int = 8) -> dict[str, list[tuple[str, float]]]:
    """Per stage, the op types that took the most time (ms summed over the profiled runs)."""
    import json
    from collections import defaultdict

    out = {}
    for f in profile_files:
        events = json.load(open(f))
        by_op: dict[str, float] = defaultdict(float)
        for e in events:
            if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
                by_op[e.get("args", {}).get("op_name", "?")] += e.get("dur", 0) / 1000.0
        stage = f.rsplit("/", 1)[-1].split("_", 1)[0]
        out[stage] = sorted(by_op.items(), key=lambda kv: -kv[1])[:top]
    return out
