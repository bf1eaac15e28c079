"""Where the test suite's time goes: torch's ONNX exports, OpenVINO's compiles, onnxruntime's sessions.

    PYTHONPATH=scripts .venv/bin/python -m pytest -q -p call_times     # writes the log
    .venv/bin/python scripts/call_times.py                              # sums it

As a pytest plugin (`-p call_times`, loaded by every pytest-xdist worker) it times each call of
`torch.onnx.export`, `openvino.Core.compile_model` (a compile, or a load from the compile cache)
and `onnxruntime.InferenceSession` and appends one line per call (kind, seconds, test) to the log,
`D3LVO_CALL_TIMES` or /tmp/d3lvo-call-times.tsv (emptied by the run's first process to load it,
so each run's log is its own). Run as a script it prints, per kind, the calls and their seconds,
and the tests that spent the most on each. docs/testing.md quotes it.
"""

from __future__ import annotations

import functools
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

LOG = Path(os.environ.get("D3LVO_CALL_TIMES", "/tmp/d3lvo-call-times.tsv"))


def _timed(kind: str, f):
    @functools.wraps(f)
    def call(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return f(*args, **kwargs)
        finally:
            test = os.environ.get("PYTEST_CURRENT_TEST", "?").split(" ")[0]
            with LOG.open("a") as log:
                log.write(f"{kind}\t{time.perf_counter() - t0:.3f}\t{test}\n")
    return call


def pytest_configure(config) -> None:
    if not os.environ.get("PYTEST_XDIST_WORKER"):  # the controller (or a run without workers) starts the log
        LOG.write_text("")
    import onnxruntime
    import torch.onnx

    torch.onnx.export = _timed("onnx_export", torch.onnx.export)
    onnxruntime.InferenceSession.__init__ = _timed("ort_session", onnxruntime.InferenceSession.__init__)
    try:
        import openvino
    except ImportError:
        return
    openvino.Core.compile_model = _timed("ov_compile_model", openvino.Core.compile_model)


def main(path: Path) -> None:
    if not path.is_file():
        sys.exit(f"{path}: no log; run pytest with -p call_times first")
    seconds, calls = defaultdict(float), defaultdict(int)
    per_test = defaultdict(lambda: defaultdict(float))
    for line in path.read_text().splitlines():
        kind, s, test = line.split("\t")
        seconds[kind] += float(s)
        calls[kind] += 1
        per_test[kind][test] += float(s)
    for kind in sorted(seconds, key=seconds.get, reverse=True):
        top = sorted(per_test[kind].items(), key=lambda kv: kv[1], reverse=True)[:3]
        print(f"{kind}: {calls[kind]} calls, {seconds[kind]:.1f} s; most in "
              + ", ".join(f"{t.split('::')[-1]} {v:.1f} s" for t, v in top))


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else LOG)
