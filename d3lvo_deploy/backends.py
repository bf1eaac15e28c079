"""Inference engines behind one small session interface: onnxruntime (the default, always
installed) and OpenVINO (the `[openvino]` extra), both reading the same exported `.onnx` files.

Why two: on 2-core CPUs OpenVINO's CPU plugin runs the flow+pose graph (gathers, grid samples,
the unrolled solver) markedly faster than onnxruntime, while onnxruntime is on par or faster on
the convolution stages; `d3lvo bench` times both in one sitting so the choice is measured on
the machine at hand.
"""

from __future__ import annotations

import numbers
import os
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .cpu import bf16_kernels, cpu_info, isa_cap
from .errors import D3LVOInputError

BACKENDS = ("onnxruntime", "openvino")
# "auto": OpenVINO where installed (faster on every stage but completion in `d3lvo bench` here:
# the bundled model 50.8 vs 81.4 ms per frame), else onnxruntime; the two agree within 1e-5
AUTO = "auto"
# the most threads a stage may ask for: far beyond any CPU's cores, but each thread an engine starts
# holds memory, and a million of them fill the machine
MOST_THREADS = 1024
# OpenVINO's CPU inference precision: f32 is exact to onnxruntime's; bf16 uses the CPU's
# AVX512_BF16 / AMX fast paths where it has them, for completion and encoder only: with the
# Gauss-Newton solver in bf16 too, held-out t_rel went from 0.68 / 0.73 % to 5.65 / 6.27 %
# (README, precision table), as fp16 exports keep that stage in fp32 for the same reason.
OV_PRECISIONS = ("f32", "bf16")
REDUCED_PRECISION_STAGES = ("completion", "encoder")
# the stage a run solves beside the others, on a thread of its own (`SessionConfig.solves_beside`)
BESIDE_STAGE = "classical"
WEIGHTED_STAGE = "flowpose_weighted"  # the flow+pose graph that takes that stage's pose
# the stages one thread short while the classical solve runs beside them, per engine (measured,
# docs/performance.md): onnxruntime's pool threads spin while they wait, so its encoder on every
# core beside the solve lost more than the split gained; OpenVINO's encoder on every core was faster
SHORT_BESIDE = {"onnxruntime": ("completion", "encoder"), "openvino": ("completion",)}

PROVIDERS = {"cpu": "CPUExecutionProvider", "cuda": "CUDAExecutionProvider", "tensorrt": "TensorrtExecutionProvider"}
# onnxruntime's GraphOptimizationLevel members, by the names --optimization takes
OPT_LEVELS = {"disable": "ORT_DISABLE_ALL", "basic": "ORT_ENABLE_BASIC", "extended": "ORT_ENABLE_EXTENDED",
              "all": "ORT_ENABLE_ALL"}


def _ort():
    """onnxruntime, imported where a session needs it rather than with this module: once its
    pybind11 module is loaded, every C++ exception in the process runs through its exception
    translators, which slows torch's exporter ~1.5x (`d3lvo bench --ckpt` exports first)."""
    import onnxruntime

    return onnxruntime


def usable_cores(topology: str = "/sys/devices/system/cpu") -> int:
    """The physical cores this process may run on (a taskset's share, not the machine's): what
    the engines take by default, one thread per core, whatever its hyperthreads."""
    try:
        cpus = sorted(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1
    cores = set()
    for cpu in cpus:
        try:  # the logical CPUs that share this one's core, e.g. "0,4" or "0-1"
            cores.add(Path(f"{topology}/cpu{cpu}/topology/thread_siblings_list").read_text().strip())
        except OSError:
            cores.add(str(cpu))
    return max(1, len(cores))


def resolve_providers(name: str) -> list[str]:
    if name not in PROVIDERS:
        raise D3LVOInputError(None, f"--provider must be one of {', '.join(PROVIDERS)}, not {name!r}")
    wanted = PROVIDERS[name]
    available = _ort().get_available_providers()
    if wanted not in available:
        warnings.warn(f"{wanted} is not available in this onnxruntime build; falling back to CPU", stacklevel=2)
        return ["CPUExecutionProvider"]
    return [wanted, "CPUExecutionProvider"] if wanted != "CPUExecutionProvider" else [wanted]


@dataclass(frozen=True)
class SessionConfig:
    provider: str = "cpu"
    threads: int = 0  # 0: OMP_NUM_THREADS where set, else the engine decides (all physical cores)
    optimization: str = "all"
    profile_dir: str | None = None
    # ORT's pool threads busy-wait between ops rather than sleep: a stage of thousands of small ops
    # then pays no wake-up per op (2-20 % less per frame, docs/performance.md). They stop when a run
    # returns (force_spinning_stop): spinning on between runs would take the 2 cores from the
    # numpy projection between stages (~120 ms instead of ~14 ms)
    spinning: bool = True
    backend: str = "onnxruntime"
    ov_precision: str = "f32"
    # threads of the flow+pose stage alone (0: as the others). A pipelined run gives it one fewer
    # than the machine has (`pipelined`)
    flowpose_threads: int = 0
    # threads of a frame's CPU half (`Odometry.prepare`); 0: `preparing_threads` decides
    prepare_threads: int = 0
    # where the model folder has the `classical` stage: solve the classical mode on a thread of its
    # own beside completion and encoder (`solves_beside`)
    classical_beside: bool = True

    @property
    def engine_threads(self) -> int:
        """The thread count handed to the engine. 0 reads OMP_NUM_THREADS, as torch and numpy do:
        it is how a container or several processes sharing a machine ask each for fewer threads
        (two threads per process on two cores spend their time waiting for each other)."""
        if self.threads:
            return self.threads
        try:  # OpenMP allows a list per nesting level ("4,2"): the outer level's count
            return max(0, int(os.environ.get("OMP_NUM_THREADS", "0").split(",")[0]))
        except ValueError:
            return 0

    @property
    def threads_taken(self) -> int:
        """The threads the engines take: `engine_threads`, else one per physical core."""
        return self.engine_threads or usable_cores()

    @property
    def preparing_threads(self) -> int:
        """Threads of a frame's CPU half (`Odometry.prepare`): `prepare_threads` where set, else
        two where the engines have two cores or more, so that the solver's frame is made beside
        the network's inputs (docs/performance.md). A pipeline sets one: its reader thread has
        one core beside the network (`pipelined`)."""
        if self.prepare_threads:
            return self.prepare_threads
        return 2 if self.threads_taken >= 2 else 1

    @property
    def solves_beside(self) -> bool:
        """The classical mode's solve runs on a thread of its own while completion and encoder run
        (`Odometry`, where the model folder has the `classical` stage): with two cores or more, on
        the CPU provider (what was measured). The
        solve's steps are thousands of small ops on one thread whichever the stage's thread count,
        so they take the second core that the network's other stages use least
        (docs/performance.md)."""
        return self.classical_beside and self.threads_taken >= 2 and self.provider == "cpu"

    def for_stage(self, stage: str) -> "SessionConfig":
        """The settings one stage's session opens with (and nothing else: two runs whose stage
        settings are equal share the stage's session, compiled graph and cache). `classical`
        runs on one thread, beside the others."""
        threads = self.flowpose_threads if stage.startswith("flowpose") and self.flowpose_threads else self.threads
        if stage == BESIDE_STAGE:
            threads = 1
        # the run-wide switches reset: a stage's session depends on its own settings only
        return replace(self, threads=threads, flowpose_threads=0, prepare_threads=0, classical_beside=True)

    def pipelined(self, depth: int = 2) -> "SessionConfig":
        """For a pipeline (`d3lvo run --pipeline`): the flow+pose stage one thread short of the
        cores, so that the reader thread's work runs beside it on a core of its own instead of
        taking turns with its threads: the stage is per-op overhead more than arithmetic, and loses
        less to one thread fewer than the reader's work takes (docs/performance.md). `depth` 3:
        the reader also runs completion and encoder, on that one core."""
        if self.flowpose_threads:
            return self
        n = self.threads_taken
        if n < 2:
            return self
        # three deep, the reader's core runs completion and encoder: the classical solve stays in the
        # flow+pose graph's batch
        return replace(self, flowpose_threads=n - 1, threads=1 if depth == 3 else self.threads, prepare_threads=1,
                       classical_beside=self.classical_beside and depth < 3)

    def resolved(self) -> "SessionConfig":
        """The same settings with "auto" replaced by the engine it picks here."""
        if self.backend != AUTO:
            return self
        # a GPU provider or an onnxruntime profile asks for onnxruntime
        ort_only = self.provider != "cpu" or self.profile_dir is not None
        use_ov = not ort_only and "openvino" in available_backends()
        return replace(self, backend="openvino" if use_ov else "onnxruntime")

    def check(self) -> None:
        for name, n, zero in (("--threads", self.threads, "OMP_NUM_THREADS where set, else all cores"),
                              ("flowpose_threads", self.flowpose_threads, "as the other stages"),
                              ("--prepare-threads", self.prepare_threads, "1 or 2 by the cores")):
            if isinstance(n, bool) or not isinstance(n, numbers.Integral):
                raise D3LVOInputError(None, f"{name} must be a whole number of threads, not {n!r}")
            if n < 0:
                raise D3LVOInputError(None, f"{name} must be 0 ({zero}) or more, not {n}")
            if n > MOST_THREADS:
                raise D3LVOInputError(None, f"{name} {n} is more than {MOST_THREADS} threads (each one an engine "
                                            "starts holds memory)")
        if self.backend not in (*BACKENDS, AUTO):
            raise D3LVOInputError(None, f"--backend must be one of {', '.join(BACKENDS)} or {AUTO}, not {self.backend!r}")
        if self.backend == AUTO:
            return self.resolved().check()
        if self.ov_precision not in OV_PRECISIONS:
            raise D3LVOInputError(None, f"--ov-precision must be one of {', '.join(OV_PRECISIONS)}, "
                                        f"not {self.ov_precision!r}")
        if self.backend == "openvino":
            if self.ov_precision == "bf16":
                info, cap = cpu_info(), isa_cap()
                if not bf16_kernels(info.isa):
                    raise D3LVOInputError(None, "--ov-precision bf16 needs a CPU with AVX512-BF16 or AMX-BF16 "
                                                f"(this one: {info.line()}): use f32, the default")
                if cap is not None and not bf16_kernels(info.isa, cap[1]):
                    raise D3LVOInputError(None, f"--ov-precision bf16 needs oneDNN's bf16 kernels, which "
                                                f"{cap[0]}={cap[1]} holds off: use f32, the default, or unset "
                                                "the variable")
            if self.provider != "cpu":
                raise D3LVOInputError(None, "--provider is onnxruntime's; the openvino backend runs on the CPU")
            if self.profile_dir:
                raise D3LVOInputError(None, "--profile writes onnxruntime profiles; use --backend onnxruntime")
        elif self.ov_precision != "f32":
            raise D3LVOInputError(None, "--ov-precision applies to --backend openvino only")


# "auto" on a short run. Measured with `scripts/start_times.py` on a 300-frame synthetic drive
# (`d3lvo run --end E` on each engine, an empty cache, then with its graphs; bundled model, AMD
# EPYC with AVX-512, 2 cores; docs/performance.md): OpenVINO, compiling first, finished 200
# frames as soon as onnxruntime (19.1 against 19.0 s) and 100 frames 3.2 s later; with its
# compiled graphs cached, 50 frames 1.0 s later and 100 frames 1.1 s sooner. So OpenVINO pays
# back after about 200 frames when it compiles and 50-100 when cached; auto takes it from about
# twice these lengths on, onnxruntime below
AUTO_MIN_FRAMES_CACHED = 150
AUTO_MIN_FRAMES = 400


def choose_engine(sc: SessionConfig, manifest: dict | None, frames: int | None,
                  pipelined: bool = False) -> tuple[SessionConfig, str]:
    """The engine a run takes, and why in words (printed by `d3lvo run`). `frames`: the run's
    length (None: a stream of unknown length, where the faster engine wins in the end);
    `pipelined`: the run's flow+pose stage is compiled for a pipeline (`SessionConfig.pipelined`)."""
    if sc.backend != AUTO:
        return sc, "asked for"
    if sc.provider != "cpu" or sc.profile_dir is not None:
        return replace(sc, backend="onnxruntime"), "auto: a GPU provider or a profile is onnxruntime's"
    if "openvino" not in available_backends():
        return replace(sc, backend="onnxruntime"), "auto: OpenVINO is not installed (the [openvino] extra)"
    ov = replace(sc, backend="openvino")
    if sc.ov_precision != "f32":
        return ov, f"auto: --ov-precision {sc.ov_precision} is OpenVINO's"
    cached = manifest is not None and openvino_compiled(ov.pipelined() if pipelined else ov, manifest)
    if frames is None:
        return ov, "auto: OpenVINO, the faster engine here, for a stream"
    need = AUTO_MIN_FRAMES_CACHED if cached else AUTO_MIN_FRAMES
    if frames >= need:
        return ov, (f"auto: OpenVINO, the faster engine here; over {frames} frames it repays its "
                    + ("load from the cache" if cached else "first compile"))
    return replace(sc, backend="onnxruntime"), (
        f"auto: {frames} frames are too few to repay OpenVINO's "
        + ("load from the cache" if cached else "first compile of this model")
        + f"; it takes OpenVINO from {need} frames on")


def _marker(sc: SessionConfig, stage: str, sha256: str) -> str:
    precision = sc.ov_precision if stage in REDUCED_PRECISION_STAGES else "f32"
    return f"{sha256[:24]}-{precision}-t{sc.engine_threads}.compiled"


def openvino_compiled(sc: SessionConfig, manifest: dict) -> bool:
    """Whether every stage of this model was compiled here before with these settings (markers
    written next to OpenVINO's own cache, which keeps no index of its own)."""
    try:
        import openvino
    except ImportError:
        return False
    cache = openvino_cache_dir(openvino.__version__)
    if cache is None:
        return False
    stages = manifest.get("stages", {})
    return all((cache / _marker(c, n, stages[n]["sha256"])).is_file() for n, c in stage_configs(stages, sc).items())


def stage_configs(stages, sc: SessionConfig) -> dict[str, SessionConfig]:
    """The stages of a model folder (names, in the manifest's order) that a run with `sc` opens,
    each with the settings its session opens with (`SessionConfig.for_stage`). Where the run
    solves the classical mode beside (`SessionConfig.solves_beside`) and the folder has that
    stage: `classical` (one thread) and `flowpose_weighted` in place of `flowpose`, and the stages
    the solve runs beside one thread short, which leaves it a core of its own (`SHORT_BESIDE`);
    else `flowpose`."""
    names = list(stages)
    beside = sc.solves_beside and BESIDE_STAGE in names and WEIGHTED_STAGE in names
    unused = {"flowpose"} if beside else {BESIDE_STAGE, WEIGHTED_STAGE}
    out = {}
    for n in names:
        if n in unused:
            continue
        out[n] = sc.for_stage(n)
        if beside and n in SHORT_BESIDE.get(sc.backend, ()):
            out[n] = replace(out[n], threads=max(1, sc.threads_taken - 1))
    return out


def available_backends() -> list[str]:
    """Installed engines, in BACKENDS order."""
    out = ["onnxruntime"]
    try:
        import openvino  # noqa: F401
    except ImportError:
        pass
    else:
        out.append("openvino")
    return out


class OrtSession:
    """One onnxruntime InferenceSession; inputs/outputs as (name, shape) and names."""

    def __init__(self, path: Path, sc: SessionConfig, stage: str, expected: dict | None = None):
        if sc.optimization not in OPT_LEVELS:
            raise D3LVOInputError(None, f"--optimization must be one of {', '.join(OPT_LEVELS)}")
        ort = _ort()
        level = getattr(ort.GraphOptimizationLevel, OPT_LEVELS[sc.optimization])
        so = ort.SessionOptions()
        so.graph_optimization_level = level
        so.intra_op_num_threads = sc.engine_threads
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.log_severity_level = 3  # errors only: optimiser notes (e.g. fp16 constant folding) are not user news
        so.add_session_config_entry("session.intra_op.allow_spinning", "1" if sc.spinning else "0")
        if sc.spinning:  # ... within a run only: stopped when it returns, so numpy has the cores again
            so.add_session_config_entry("session.force_spinning_stop", "1")
        if sc.profile_dir:
            os.makedirs(sc.profile_dir, exist_ok=True)
            so.enable_profiling = True
            so.profile_file_prefix = str(Path(sc.profile_dir) / stage)
        providers = resolve_providers(sc.provider)
        cached = ort_cache_file(sc, stage, expected) if providers == ["CPUExecutionProvider"] else None
        self.sess = None
        if cached is not None and cached.is_file():
            # optimised here before: load it as is, skipping the optimiser (most of a cold start)
            so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
            try:
                self.sess = ort.InferenceSession(str(cached), so, providers=providers)
            except Exception:  # noqa: BLE001 - a damaged cache entry: optimise afresh
                cached.unlink(missing_ok=True)
                so.graph_optimization_level = level
        if self.sess is None:
            tmp = None
            if cached is not None:
                tmp = cached.with_name(f".{cached.name}.{os.getpid()}.tmp")
                so.optimized_model_filepath = str(tmp)
            try:
                self.sess = ort.InferenceSession(str(path), so, providers=providers)
            except Exception as e:  # onnxruntime raises its own exception types
                if tmp is not None:  # perhaps only the cache could not be written (disk full, folder gone)
                    so.optimized_model_filepath = ""
                    tmp.unlink(missing_ok=True)
                    tmp = None
                    try:
                        self.sess = ort.InferenceSession(str(path), so, providers=providers)
                    except Exception:  # noqa: BLE001 - the model itself: report the first error
                        pass
                if self.sess is None:
                    raise D3LVOInputError(path, f"onnxruntime cannot load it ({str(e).splitlines()[0][:200]})") from None
            if tmp is not None and tmp.is_file():
                try:
                    os.replace(tmp, cached)
                except OSError:
                    tmp.unlink(missing_ok=True)
        self.inputs = [(i.name, list(i.shape)) for i in self.sess.get_inputs()]
        self.outputs = [o.name for o in self.sess.get_outputs()]

    def run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        return self.sess.run(None, feeds)

    def end_profiling(self) -> str:
        return self.sess.end_profiling()


def openvino_reason(e: Exception) -> str:
    """The line of an OpenVINO error that says what failed: its text opens with lines naming the
    source files it passed through ("Exception from src/inference/src/cpp/core.cpp:132:") and
    ends with the reason."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    said = [ln for ln in lines if not ln.startswith("Exception from ")]
    return ((said or lines or [type(e).__name__])[-1])[:200]


class OpenVinoSession:
    """One OpenVINO compiled model on the CPU, latency mode (one stream: frames come one by one)."""

    _core = None

    def __init__(self, path: Path, sc: SessionConfig, stage: str, expected: dict | None = None):
        from .extras import require

        require("openvino", what="--backend openvino")
        import openvino as ov

        if OpenVinoSession._core is None:
            OpenVinoSession._core = ov.Core()
        precision = sc.ov_precision if stage in REDUCED_PRECISION_STAGES else "f32"
        config = {"PERFORMANCE_HINT": "LATENCY", "NUM_STREAMS": "1", "INFERENCE_PRECISION_HINT": precision}
        if stage == BESIDE_STAGE:  # unpinned: pinned, its thread shared a core with another stage's
            config["ENABLE_CPU_PINNING"] = False
        if sc.engine_threads:
            config["INFERENCE_NUM_THREADS"] = str(sc.engine_threads)
        cache = openvino_cache_dir(ov.__version__)
        if cache is not None:
            config["CACHE_DIR"] = str(cache)
        try:
            self.compiled = OpenVinoSession._core.compile_model(str(path), "CPU", config)
        except Exception as e:  # OpenVINO raises RuntimeError with a long multi-line text
            raise D3LVOInputError(path, f"OpenVINO cannot load it ({openvino_reason(e)})") from None
        if cache is not None and expected and expected.get("sha256"):
            try:
                (cache / _marker(sc, stage, expected["sha256"])).touch()
            except OSError:
                pass
        self.request = self.compiled.create_infer_request()
        # a port may carry several tensor names (a converted graph's Cast keeps both): report the
        # one the manifest uses, so the folder check compares like with like
        want_in = [i["name"] for i in (expected or {}).get("inputs", [])]
        want_out = [o["name"] for o in (expected or {}).get("outputs", [])]
        self.inputs = [(_port_name(p, want_in, k), [d.get_length() if d.is_static else "?" for d in p.get_partial_shape()])
                       for k, p in enumerate(self.compiled.inputs)]
        self.outputs = [_port_name(p, want_out, k) for k, p in enumerate(self.compiled.outputs)]

    def run(self, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
        # read in place rather than copied into the request (a copy per input per run: the
        # solver's full-resolution image pyramids are megabytes, docs/performance.md); the call is
        # synchronous, so the arrays are not changed while it reads them
        self.request.infer({k: np.ascontiguousarray(v) for k, v in feeds.items()}, share_inputs=True)
        # the request's output tensors are reused by the next run: copy them out
        return [self.request.get_output_tensor(k).data.copy() for k in range(len(self.outputs))]

    def end_profiling(self) -> str:
        return ""


def ort_cache_file(sc: SessionConfig, stage: str, expected: dict | None) -> Path | None:
    """Where onnxruntime keeps this stage's optimised graph (full optimisation only, no
    profiling): keyed by the stage's hash (the manifest's), the thread count, the onnxruntime
    version and the CPU, since the optimised graph holds kernels chosen for them."""
    if sc.optimization != "all" or sc.profile_dir or not expected or not expected.get("sha256"):
        return None
    folder = engine_cache_dir("onnxruntime", _ort().__version__)
    return None if folder is None else folder / f"{stage}-{expected['sha256'][:24]}-t{sc.engine_threads}.onnx"


def openvino_cache_dir(version: str) -> Path | None:
    return engine_cache_dir("openvino", version)


def engine_cache_dir(engine: str, version: str) -> Path | None:
    """Where an engine keeps compiled or optimised models between runs: compiling the point
    solver's graph takes OpenVINO ~10 s on 2 cores, onnxruntime's optimiser ~1.5 s; loading either
    from the cache well under a second. The folder names the engine version and the CPU, so an
    entry is never read by another version or on another machine sharing a home folder.
    `D3LVO_CACHE` moves it; None (no cache) where it cannot be written."""
    import hashlib

    from .cpu import cpu_info

    root = Path(os.environ.get("D3LVO_CACHE") or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "d3lvo")
    cpu = hashlib.sha1(cpu_info().line().encode()).hexdigest()[:10]
    folder = root / f"{engine}-{''.join(c if c.isalnum() or c == '.' else '_' for c in version)}-{cpu}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return folder if os.access(folder, os.W_OK) else None


def _port_name(port, wanted: list[str], k: int) -> str:
    names = port.get_names()
    if k < len(wanted) and wanted[k] in names:
        return wanted[k]
    return port.get_any_name()


def open_session(path: Path, sc: SessionConfig, stage: str, expected: dict | None = None) -> OrtSession | OpenVinoSession:
    """`expected`: the manifest's entry for the stage (its input/output names)."""
    return (OpenVinoSession if sc.backend == "openvino" else OrtSession)(path, sc, stage, expected)
