"""How long `d3lvo run` takes to start: its first pose, and the whole run, with and without the
engines' cached graphs.

    .venv/bin/python scripts/start_times.py [SEQUENCE] [--rounds 2] [--later 2] [--backend auto openvino] [--end M]

For each round and engine: a run with an empty cache (a scratch `D3LVO_CACHE`: OpenVINO compiles,
onnxruntime optimises), then `--later` runs that find the first one's graphs there. Each run is
the `d3lvo` command beside this interpreter, timed from its start to the first line of its pose
file (it writes a pose per frame as it goes) and to its exit; `--end M` runs the frames before M only
(`d3lvo run --end`, one past the last frame). SEQUENCE defaults to the 20 real KITTI frames in ../shared/data.
docs/performance.md quotes it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "kitti_raw_snippet" / "sequences" / "r0926"


def timed_run(cmd: list[str], poses: Path, env: dict) -> tuple[float | None, float, int, str]:
    """(seconds to the first pose line, seconds to exit, exit code, the line naming the engine)."""
    poses.unlink(missing_ok=True)
    with tempfile.TemporaryFile("w+") as log:  # a file, not a pipe: a long run's output never blocks it
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, text=True)
        first = None
        while p.poll() is None:
            if first is None and poses.exists() and poses.stat().st_size > 0:
                first = time.perf_counter() - t0
            time.sleep(0.02)
        done = time.perf_counter() - t0
        log.seek(0)
        said = log.read()
    engine = next((ln.strip() for ln in said.splitlines() if ln.strip().startswith("model ")), said.strip()[-200:])
    return first, done, p.returncode, engine


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", nargs="?", type=Path, default=REAL)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--later", type=int, default=2, help="runs after each empty-cache run")
    ap.add_argument("--backend", nargs="+", default=["auto", "openvino"])
    ap.add_argument("--end", type=int, help="one past the last frame to run (d3lvo run --end)")
    a = ap.parse_args()
    if not a.sequence.is_dir():
        sys.exit(f"error: {a.sequence}: no such sequence folder")
    d3lvo = Path(sys.executable).with_name("d3lvo")
    with tempfile.TemporaryDirectory() as tmp:
        cache, poses = Path(tmp) / "cache", Path(tmp) / "poses.txt"
        env = dict(os.environ, D3LVO_CACHE=str(cache))
        for r in range(a.rounds):
            for backend in a.backend:
                shutil.rmtree(cache, ignore_errors=True)
                for k in range(1 + a.later):
                    first, done, rc, engine = timed_run(
                        [str(d3lvo), "run", str(a.sequence), "--out", str(poses), "--backend", backend,
                         *(["--end", str(a.end)] if a.end is not None else [])], poses, env)
                    if rc != 0:
                        sys.exit(f"error: d3lvo run --backend {backend} exited with {rc}: {engine}")
                    which = "empty cache" if k == 0 else "cached"
                    print(f"round {r + 1}, --backend {backend}, {which}: first pose "
                          f"{'-' if first is None else f'{first:.1f} s'}, done {done:.1f} s")
                    if r == 0 and k == 0:
                        print(f"  {engine}")


if __name__ == "__main__":
    main()
