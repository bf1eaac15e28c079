"""numpy's BLAS on one thread for the runtime's per-frame work.

OpenBLAS's worker threads keep spinning for a while after a multi-threaded call, such as the
small matrix products of the scan's projection. On a 2-core vehicle computer they then hold a
core while the inference engine runs the frame's stages: measured on the real frames, OpenVINO's
completion and encoder took 1.6x as long and its whole frame 1.26-1.28x (docs/performance.md). The
runtime's numpy work is a few vector passes per frame, which gain nothing from BLAS threads.
"""

from __future__ import annotations

from contextlib import AbstractContextManager

_controller = None


def one_blas_thread() -> AbstractContextManager:
    """A context holding numpy's BLAS to one thread (restored on exit); threadpoolctl's
    controller, found once (a lookup of the loaded libraries takes ~0.1 ms, a limit ~7 us)."""
    global _controller
    if _controller is None:
        from threadpoolctl import ThreadpoolController

        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")
