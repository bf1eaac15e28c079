"""onnxruntime with and without its pool threads spinning during a run, in one process.

Two Odometry instances on the same frames, taking turns frame by frame (the order swapped every
frame), so that a VM's drift reaches both sides alike; separate bench runs minutes apart differ
by more than the effect. Prints the median per stage and the whole step, in ms.

    .venv/bin/python scripts/ort_spinning_ab.py [MODEL_DIR] [--passes 3] [--seq-dir DIR]

MODEL_DIR defaults to the bundled model; frames default to the real KITTI frames.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from d3lvo_deploy.backends import SessionConfig
from d3lvo_deploy.bundled import bundled_model_dir, find_real_frames
from d3lvo_deploy.cpu import cpu_info
from d3lvo_deploy.odometry import Odometry
from d3lvo_deploy.sequence import KittiSequence


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir", nargs="?", default=None)
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--seq-dir", default=None)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    seq = KittiSequence.open(a.seq_dir or find_real_frames())
    frames = [(seq.image(i), seq.scan(i)) for i in range(len(seq))]
    model = a.model_dir or bundled_model_dir()
    sides = {name: Odometry(model, seq.calib, SessionConfig(threads=a.threads, backend="onnxruntime", spinning=spin))
             for name, spin in (("spinning", True), ("sleeping", False))}
    times: dict[str, dict[str, list[float]]] = {name: {} for name in sides}
    for p in range(a.passes):
        for i, (image, scan) in enumerate(frames):
            order = list(sides.items()) if (i + p) % 2 == 0 else list(sides.items())[::-1]
            for name, odo in order:
                t = time.perf_counter()
                odo.step(image, scan)
                step_ms = (time.perf_counter() - t) * 1e3
                if p == 0 and i < 3:  # warm-up
                    continue
                for stage, ms in {**odo.last_timing.ms, "step": step_ms}.items():
                    times[name].setdefault(stage, []).append(ms)
    print(f"CPU: {cpu_info().line()}; {model}; {a.threads} threads, {a.passes} passes over {len(frames)} frames")
    for name, stages in times.items():
        print(f"{name:9s} " + "  ".join(f"{s} {np.median(v):.1f}" for s, v in stages.items()))


if __name__ == "__main__":
    main()
