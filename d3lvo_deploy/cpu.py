"""What the CPU is and what it can do, so every speed figure carries its machine: the model
name, the vector extensions that decide which kernels run (AVX2 / AVX-512 / VNNI / BF16 / AMX),
and a measured single-precision GEMM peak to put per-stage GFLOP/s against."""

from __future__ import annotations

import os
import platform
import time
from dataclasses import dataclass

import numpy as np

# /proc/cpuinfo flag -> the name users know, in the order they matter for inference kernels
ISA_FLAGS = (("avx2", "AVX2"), ("fma", "FMA"), ("avx512f", "AVX-512"), ("avx512_vnni", "AVX512-VNNI"),
             ("avx_vnni", "AVX-VNNI"), ("avx512_bf16", "AVX512-BF16"), ("avx512_fp16", "AVX512-FP16"),
             ("amx_bf16", "AMX-BF16"), ("amx_int8", "AMX-INT8"))


@dataclass(frozen=True)
class CpuInfo:
    model: str
    logical_cores: int
    isa: tuple[str, ...]

    def line(self) -> str:
        return f"{self.model}, {self.logical_cores} cores, {' '.join(self.isa) or 'no AVX2'}"


def cpu_info(cpuinfo_path: str = "/proc/cpuinfo") -> CpuInfo:
    model, flags = platform.processor() or platform.machine(), set()
    try:
        with open(cpuinfo_path) as fh:
            for line in fh:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name":
                    model = value.strip()
                elif key == "flags" and not flags:
                    flags = set(value.split())
    except OSError:
        pass
    return CpuInfo(model=model, logical_cores=os.cpu_count() or 1,
                   isa=tuple(name for flag, name in ISA_FLAGS if flag in flags))


# oneDNN's ISA caps below its bf16 kernels (`ONEDNN_MAX_CPU_ISA`, or the older name
# `DNNL_MAX_CPU_ISA`; OpenVINO's CPU plugin honours them): under them OpenVINO has no native bf16
# kernel, though the CPU's flags list the extension
_BELOW_BF16 = ("SSE41", "AVX", "AVX2", "AVX2_VNNI", "AVX2_VNNI_2", "AVX512_CORE", "AVX512_CORE_VNNI")
BF16_ISA = ("AVX512-BF16", "AMX-BF16")
ISA_CAP_VARIABLES = ("ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA")


def isa_cap(env: dict | None = None) -> tuple[str, str] | None:
    """(variable, value) of the oneDNN ISA cap set in `env` (default os.environ), if any."""
    env = os.environ if env is None else env
    return next(((k, env[k]) for k in ISA_CAP_VARIABLES if env.get(k, "").strip()), None)


def bf16_kernels(isa: tuple[str, ...], max_isa: str | None = None) -> bool:
    """Whether OpenVINO has native bf16 kernels here: the CPU has AVX512-BF16 or AMX-BF16 and
    oneDNN is not held below them (`max_isa`, the value of `isa_cap`). Held to its AVX2 kernels,
    OpenVINO finds no bf16 kernel for some ops and cannot compile the graph
    (docs/performance.md)."""
    return bool(set(BF16_ISA) & set(isa)) and (max_isa or "").strip().upper() not in _BELOW_BF16


def gemm_peak_gflops(n: int = 1024, repeats: int = 8) -> float:
    """Best-of single-precision GEMM rate of numpy's BLAS (all cores, as the bench's threads on
    a 2-core vehicle computer): the ceiling a convolution-bound graph could approach."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    a @ b  # warm-up: thread pool and caches
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n ** 3 / best / 1e9
