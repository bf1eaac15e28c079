"""Engines behind the runtime (onnxruntime, OpenVINO), the CPU report and the FLOP count of `d3lvo bench`."""

import importlib.util
import json

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper
from typer.testing import CliRunner

from cli.main import app
from d3lvo_deploy import backends
from d3lvo_deploy.backends import SessionConfig, openvino_reason
from d3lvo_deploy.cpu import CpuInfo, bf16_kernels, cpu_info, isa_cap
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.manifest import for_engine
from d3lvo_deploy.onnx_model import StageModel
from d3lvo_deploy.pipeline import RunConfig, prepare_run, run_sequence
from d3lvo_deploy.poses import read_poses
from d3lvo_deploy.sequence import KittiSequence
from export.flops import graph_flops

runner = CliRunner()


def test_cpu_info_reads_model_and_vector_extensions(tmp_path):
    f = tmp_path / "cpuinfo"
    f.write_text("processor\t: 0\nmodel name\t: Example CPU 9000\n"
                 "flags\t\t: fpu sse2 avx2 fma avx512f avx512_vnni amx_bf16 amx_tile\n\n"
                 "processor\t: 1\nmodel name\t: Example CPU 9000\nflags\t\t: fpu\n")
    info = cpu_info(str(f))
    assert info.model == "Example CPU 9000"
    assert info.isa == ("AVX2", "FMA", "AVX-512", "AVX512-VNNI", "AMX-BF16")  # first core's flags, known names only
    f.write_text("model name\t: Old CPU\nflags\t\t: fpu sse2\n")
    assert cpu_info(str(f)).isa == () and "no AVX2" in cpu_info(str(f)).line()


def test_bf16_kernels_need_the_extension_and_onednn_not_held_below_them():
    assert bf16_kernels(("AVX2", "FMA", "AVX-512", "AVX512-BF16"))
    assert bf16_kernels(("AVX2", "AMX-BF16"), "ALL") and bf16_kernels(("AMX-BF16",), "avx512_core_amx")
    assert not bf16_kernels(("AVX2", "FMA"))  # an AVX2-only CPU
    assert not bf16_kernels(("AVX2", "FMA", "AVX-512", "AVX512-VNNI"))  # AVX-512 without its bf16 extension
    assert not bf16_kernels(("AVX2", "AVX-512", "AVX512-BF16"), "AVX2")  # oneDNN held to its AVX2 kernels
    assert not bf16_kernels(("AVX512-BF16",), " avx2_vnni ")
    assert not bf16_kernels(("AVX-512", "AVX512-BF16"), "AVX512_CORE")  # held below the bf16 kernels
    assert bf16_kernels(("AVX-512", "AVX512-BF16"), "AVX512_CORE_BF16")
    assert isa_cap({"DNNL_MAX_CPU_ISA": "AVX2"}) == ("DNNL_MAX_CPU_ISA", "AVX2")  # oneDNN's older name
    assert isa_cap({"ONEDNN_MAX_CPU_ISA": "AVX2", "DNNL_MAX_CPU_ISA": "ALL"})[0] == "ONEDNN_MAX_CPU_ISA"
    assert isa_cap({"ONEDNN_MAX_CPU_ISA": " "}) is None and isa_cap({}) is None


def test_bf16_on_a_cpu_without_it_is_one_clear_error(monkeypatch):
    """OpenVINO asked for bf16 where it has no native bf16 kernels (held to its AVX2 ones, it
    cannot compile the encoder's Softmax): the run says so before any graph is opened."""
    monkeypatch.delenv("ONEDNN_MAX_CPU_ISA", raising=False)
    monkeypatch.delenv("DNNL_MAX_CPU_ISA", raising=False)
    monkeypatch.setattr(backends, "cpu_info", lambda: CpuInfo("Example AVX2 CPU", 2, ("AVX2", "FMA")))
    with pytest.raises(D3LVOInputError, match=r"bf16 needs a CPU with AVX512-BF16 or AMX-BF16 \(this one: "
                                              r"Example AVX2 CPU, 2 cores, AVX2 FMA\): use f32"):
        SessionConfig(backend="openvino", ov_precision="bf16").check()
    SessionConfig(backend="openvino").check()  # f32 runs anywhere
    monkeypatch.setattr(backends, "cpu_info", lambda: CpuInfo("Example CPU", 2, ("AVX2", "AVX-512", "AVX512-BF16")))
    SessionConfig(backend="openvino", ov_precision="bf16").check()
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    with pytest.raises(D3LVOInputError, match="bf16 kernels, which ONEDNN_MAX_CPU_ISA=AVX2 holds off"):
        SessionConfig(backend="openvino", ov_precision="bf16").check()
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "ALL")
    SessionConfig(backend="openvino", ov_precision="bf16").check()


def test_an_openvino_load_error_names_the_file_and_the_reason(small_model, monkeypatch):
    """What `d3lvo run` prints when OpenVINO cannot compile a stage: the file and OpenVINO's reason,
    not the source file its text opens with."""
    pytest.importorskip("openvino")
    import openvino as ov

    def refuse(self, path, *args, **kwargs):
        raise RuntimeError("Exception from src/inference/src/cpp/core.cpp:132:\n"
                           "Exception from src/inference/src/dev/plugin.cpp:59:\n"
                           "Supported primitive descriptors list is empty for node: /encoder/Softmax type: Softmax\n")

    monkeypatch.setattr(ov.Core, "compile_model", refuse)
    monkeypatch.setattr(backends.OpenVinoSession, "_core", None)
    _, onnx_dir = small_model
    with pytest.raises(D3LVOInputError) as e:
        StageModel(onnx_dir, SessionConfig(backend="openvino"))
    assert str(e.value).startswith(str(onnx_dir / "completion.onnx"))
    assert str(e.value).endswith("OpenVINO cannot load it (Supported primitive descriptors list is empty for node: "
                                 "/encoder/Softmax type: Softmax)")


def test_openvino_errors_name_the_reason_not_the_source_file():
    text = ("Exception from src/inference/src/cpp/core.cpp:132:\nException from src/inference/src/dev/plugin.cpp:59:\n"
            "Check '!getSupportedPrimitiveDescriptors().empty()' failed at src/plugins/intel_cpu/src/node.cpp:345:\n"
            "Supported primitive descriptors list is empty for node: /AveragePool type: Pooling\n\n\n")
    assert openvino_reason(RuntimeError(text)) == "Supported primitive descriptors list is empty for node: /AveragePool type: Pooling"
    assert openvino_reason(RuntimeError("Exception from src/frontends/onnx/frontend/src/frontend.cpp:1:")) == \
        "Exception from src/frontends/onnx/frontend/src/frontend.cpp:1:"  # nothing else said: that line
    assert openvino_reason(RuntimeError("")) == "RuntimeError"


def test_flop_count_by_hand(tmp_path):
    """Conv 3->8, 3x3, pad 1 on 1x3x16x16: 2*8*16*16*3*9 FLOPs; MatMul (4,5)x(5,6): 2*4*6*5; Relu: none."""
    w = helper.make_tensor("w", TensorProto.FLOAT, [8, 3, 3, 3], np.zeros(8 * 27, np.float32))
    b = helper.make_tensor("b", TensorProto.FLOAT, [5, 6], np.zeros(30, np.float32))
    nodes = [helper.make_node("Conv", ["x", "w"], ["y"], pads=[1, 1, 1, 1]),
             helper.make_node("Relu", ["y"], ["z"]),
             helper.make_node("MatMul", ["a", "b"], ["c"])]
    g = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 16, 16]),
                                       helper.make_tensor_value_info("a", TensorProto.FLOAT, [4, 5])],
                          [helper.make_tensor_value_info("z", TensorProto.FLOAT, None),
                           helper.make_tensor_value_info("c", TensorProto.FLOAT, None)], [w, b])
    onnx.save(helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)]), str(tmp_path / "g.onnx"))
    assert graph_flops(tmp_path / "g.onnx") == 2 * 8 * 16 * 16 * 3 * 9 + 2 * 4 * 6 * 5


def test_manifest_records_stage_flops(small_model):
    _, onnx_dir = small_model
    m = json.loads((onnx_dir / "manifest.json").read_text())
    for st in m["stages"].values():
        assert st["gflops"] == round(graph_flops(onnx_dir / st["file"]) / 1e9, 4) > 0


def test_session_config_errors():
    for sc, words in [(SessionConfig(backend="tvm"), "--backend must be one of"),
                      (SessionConfig(ov_precision="bf16"), "openvino only"),
                      (SessionConfig(backend="openvino", provider="cuda"), "CPU"),
                      (SessionConfig(backend="openvino", profile_dir="/tmp/x"), "onnxruntime profiles"),
                      (SessionConfig(threads=-1), "--threads must be 0 .* or more, not -1"),
                      (SessionConfig(prepare_threads=-2), r"--prepare-threads must be 0 \(1 or 2 by the cores\) or more"),
                      (SessionConfig(flowpose_threads=-1), r"flowpose_threads must be 0 \(as the other stages\)"),
                      # an API caller's threads: whole numbers, and not a million (each engine thread holds memory)
                      (SessionConfig(threads=1.5), "--threads must be a whole number of threads, not 1.5"),
                      (SessionConfig(threads="2"), "--threads must be a whole number of threads, not '2'"),
                      (SessionConfig(prepare_threads=True), "--prepare-threads must be a whole number of threads"),
                      (SessionConfig(threads=10**6), r"--threads 1000000 is more than 1024 threads \(each one")]:
        with pytest.raises(D3LVOInputError, match=words):
            sc.check()
    SessionConfig(threads=1024).check()  # the most it takes
    with pytest.raises(D3LVOInputError, match="is more than"):
        SessionConfig(threads=1025).check()


needs_openvino = pytest.mark.skipif(importlib.util.find_spec("openvino") is None,
                                    reason="the [openvino] extra is not installed")


def test_bench_profile_lists_only_this_runs_ops(small_model, small_synth, tmp_path):
    """--profile into a folder that holds an earlier profile (its stage named so, with an op no graph
    has) and another JSON file: the summary lists this run's stages and ops only, and neither
    stops it after the benching."""
    _, onnx_dir = small_model
    prof = tmp_path / "prof"
    prof.mkdir()
    stale = [{"cat": "Node", "name": "x_kernel_time", "dur": 10**9, "args": {"op_name": "StaleOp"}}]
    (prof / "classical_2020-01-01_00-00-00.json").write_text(json.dumps(stale))
    (prof / "manifest.json").write_text((onnx_dir / "manifest.json").read_text())
    r = runner.invoke(app, ["bench", "--onnx", str(onnx_dir), "--seq-dir", str(small_synth), "--runs", "1",
                            "--threads", "1", "--no-torch", "--json", "--backend", "onnxruntime", "--profile", str(prof)])
    assert r.exit_code == 0, r.output
    ops = json.loads(r.stdout)["top_ops_ms"]
    assert set(ops) == {"completion", "encoder", "flowpose"}, ops  # the small model has no classical stage
    assert "Conv" in {op for op, _ in ops["encoder"]} and "StaleOp" not in json.dumps(ops)


@needs_openvino
def test_openvino_outputs_equal_onnxruntime(small_model, small_synth):
    """Same folder, same inputs: every stage output of OpenVINO (f32) equals onnxruntime's."""
    from export.quantize import calibration_feeds

    _, onnx_dir = small_model
    ort_m, ov_m = StageModel(onnx_dir), StageModel(onnx_dir, SessionConfig(backend="openvino", threads=1))
    assert ov_m.geometric and ov_m.encoder_takes_lidar
    for stage, items in calibration_feeds(onnx_dir, [small_synth], max_frames=3).items():
        for fd in items:
            a, b = ort_m.run(stage, fd), ov_m.run(stage, fd)
            assert a.keys() == b.keys()
            for k in a:
                np.testing.assert_allclose(b[k], a[k], atol=1e-4 * max(1.0, float(np.abs(a[k]).max())), err_msg=k)


@needs_openvino
def test_openvino_trajectory_and_parity(small_model, small_synth, tmp_path):
    from export.parity import POSE_R_TOL, POSE_T_TOL, run_parity

    ck, onnx_dir = small_model
    seq = KittiSequence.open(small_synth)
    run_sequence(seq, onnx_dir, RunConfig(out=tmp_path / "ort.txt"))
    run_sequence(seq, onnx_dir, RunConfig(out=tmp_path / "ov.txt"), SessionConfig(backend="openvino"))
    a, b = read_poses(tmp_path / "ort.txt").poses, read_poses(tmp_path / "ov.txt").poses
    assert np.linalg.norm(a[-1, :3, 3]) > 1.0  # the clip moves: equality is not trivially met
    np.testing.assert_allclose(b[:, :3, 3], a[:, :3, 3], atol=1e-5)
    np.testing.assert_allclose(b[:, :3, :3], a[:, :3, :3], atol=1e-5)
    rep = run_parity(ck, onnx_dir, small_synth, frames=3, sc=SessionConfig(backend="openvino"))
    assert rep.passed and rep.reference_t_m <= POSE_T_TOL and rep.reference_r_deg <= POSE_R_TOL, rep.to_dict()


def test_bench_rows_take_the_graph_each_row_times():
    """By hand: with the classical solve timed beside, flow+pose is the weighted graph and the
    beside row the classical one; the total is a frame's graphs, the beside row among them."""
    from cli.bench_cmd import _row_gflops
    from d3lvo_deploy.backends import BESIDE_STAGE, WEIGHTED_STAGE
    from d3lvo_deploy.bench import BESIDE_ROW

    g = {"completion": 0.3, "encoder": 0.7, "flowpose": 0.92, WEIGHTED_STAGE: 0.91, BESIDE_STAGE: 0.01}
    assert _row_gflops(g, beside=True) == {"completion": 0.3, "encoder": 0.7, "flowpose": 0.91, BESIDE_ROW: 0.01,
                                           "total": pytest.approx(1.92)}
    assert _row_gflops(g, beside=False) == {"completion": 0.3, "encoder": 0.7, "flowpose": 0.92,
                                            "total": pytest.approx(1.92)}


@needs_openvino
def test_cli_bench_times_both_engines(small_model, small_synth):
    _, onnx_dir = small_model
    r = runner.invoke(app, ["bench", "--onnx", str(onnx_dir), "--seq-dir", str(small_synth), "--runs", "1",
                            "--threads", "1", "--no-torch", "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert set(d["backends"]) == {"onnxruntime", "openvino"}
    assert d["best_backend"] == min(d["backends"], key=lambda b: d["backends"][b]["total_ms_median"])
    assert d["cpu"]["model"] == cpu_info().model and d["gemm_peak_gflops"] > 0
    m = json.loads((onnx_dir / "manifest.json").read_text())
    assert d["stage_gflops"] == {k: st["gflops"] for k, st in m["stages"].items()}
    # each timed row's GFLOP under the row's own name (this model times no classical solve beside)
    assert d["row_gflop"] == {"completion": d["stage_gflops"]["completion"], "encoder": d["stage_gflops"]["encoder"],
                              "flowpose": d["stage_gflops"]["flowpose"],
                              "total": pytest.approx(sum(d["stage_gflops"][k] for k in ("completion", "encoder",
                                                                                         "flowpose")))}
    r = runner.invoke(app, ["bench", "--onnx", str(onnx_dir), "--seq-dir", str(small_synth), "--runs", "1",
                            "--backend", "openvino", "--no-torch"])
    assert r.exit_code == 0, r.output
    assert "CPU: " in r.output and "GFLOP/s" in r.output and "openvino:" in r.output and "onnxruntime:" not in r.output


@needs_openvino
def test_cli_run_with_openvino(small_model, small_synth, tmp_path):
    _, onnx_dir = small_model
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out",
                            str(tmp_path / "p.txt"), "--backend", "openvino"])
    assert r.exit_code == 0, r.output
    assert len(read_poses(tmp_path / "p.txt")) == len(KittiSequence.open(small_synth))
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out",
                            str(tmp_path / "q.txt"), "--backend", "openvino", "--ov-precision", "fp8"])
    assert r.exit_code == 1 and "--ov-precision must be one of" in r.output


def test_auto_picks_openvino_where_installed(small_model):
    _, onnx_dir = small_model
    expect = "openvino" if importlib.util.find_spec("openvino") else "onnxruntime"
    assert SessionConfig(backend="auto").resolved().backend == expect
    assert StageModel(onnx_dir, SessionConfig(backend="auto", threads=1)).backend == expect
    assert SessionConfig(backend="onnxruntime").resolved().backend == "onnxruntime"
    # a GPU provider is onnxruntime's: auto does not turn it into an error
    assert SessionConfig(backend="auto", provider="cuda").resolved().backend == "onnxruntime"


@needs_openvino
def test_bf16_leaves_the_solver_in_f32(small_model):
    """--ov-precision bf16 is for the convolution stages: the Gauss-Newton solver stays f32 (in
    bf16 it lost held-out accuracy, README)."""
    _, onnx_dir = small_model
    sc = SessionConfig(backend="openvino", ov_precision="bf16")
    cap = isa_cap()
    if not bf16_kernels(cpu_info().isa, cap and cap[1]):  # refused here
        with pytest.raises(D3LVOInputError, match="--ov-precision bf16 needs"):
            StageModel(onnx_dir, sc)
        return
    m = StageModel(onnx_dir, sc)
    hint = lambda stage: str(m.sessions[stage].compiled.get_property("INFERENCE_PRECISION_HINT"))  # noqa: E731
    assert "float32" in hint("flowpose")
    assert "bfloat16" in hint("encoder") and "bfloat16" in hint("completion")


def test_openvino_compiled_models_are_cached_per_engine_and_cpu(small_model, tmp_path, monkeypatch):
    """A second load reads the compiled graphs from D3LVO_CACHE instead of compiling again (the
    folder names the OpenVINO version and the CPU), and computes the same numbers."""
    pytest.importorskip("openvino")
    from d3lvo_deploy.backends import openvino_cache_dir

    monkeypatch.setenv("D3LVO_CACHE", str(tmp_path / "cache"))
    _, onnx_dir = small_model
    first = StageModel(onnx_dir, SessionConfig(backend="openvino"))
    folders = list((tmp_path / "cache").iterdir())
    assert len(folders) == 1 and folders[0] == openvino_cache_dir(__import__("openvino").__version__)
    blobs = sorted(folders[0].glob("*.blob"))
    assert len(blobs) >= 3  # completion, encoder, flowpose
    stamps = [b.stat().st_mtime_ns for b in blobs]
    second = StageModel(onnx_dir, SessionConfig(backend="openvino"))
    assert [b.stat().st_mtime_ns for b in sorted(folders[0].glob("*.blob"))] == stamps  # read, not rewritten
    rgb = np.random.default_rng(0).normal(size=(1, 3, first.height, first.width)).astype(np.float32)
    inv = np.zeros((1, 1, first.height, first.width), np.float32)
    np.testing.assert_array_equal(first.complete(rgb, inv), second.complete(rgb, inv))


def test_auto_keeps_a_short_run_off_an_uncompiled_openvino(small_model, tmp_path, monkeypatch):
    """auto: onnxruntime for a run too short to repay OpenVINO's first compile (or, once cached,
    its slower load), OpenVINO for a long run or a stream; the reason is given in words."""
    pytest.importorskip("openvino")
    from d3lvo_deploy.backends import AUTO_MIN_FRAMES, AUTO_MIN_FRAMES_CACHED, choose_engine
    from d3lvo_deploy.manifest import load_manifest

    monkeypatch.setenv("D3LVO_CACHE", str(tmp_path / "cache"))
    _, onnx_dir = small_model
    manifest = load_manifest(onnx_dir)
    auto = SessionConfig(backend="auto")
    sc, why = choose_engine(auto, manifest, 20)
    assert sc.backend == "onnxruntime" and "20 frames are too few" in why
    assert choose_engine(auto, manifest, AUTO_MIN_FRAMES)[0].backend == "openvino"
    assert choose_engine(auto, manifest, None)[0].backend == "openvino"  # a stream of unknown length
    assert choose_engine(SessionConfig(backend="onnxruntime"), manifest, 10**6) == (
        SessionConfig(backend="onnxruntime"), "asked for")
    assert choose_engine(auto, manifest, AUTO_MIN_FRAMES_CACHED)[0].backend == "onnxruntime"
    StageModel(onnx_dir, SessionConfig(backend="openvino"))  # compiles, and the cache remembers it
    sc, why = choose_engine(auto, manifest, AUTO_MIN_FRAMES_CACHED)
    assert sc.backend == "openvino" and "load from the cache" in why
    # a short run stays on onnxruntime: even a cached OpenVINO loads slower than it
    assert choose_engine(auto, manifest, 20)[0].backend == "onnxruntime"
    # threads are part of what OpenVINO compiled: another count is another compile
    assert choose_engine(SessionConfig(backend="auto", threads=SessionConfig().engine_threads + 1), manifest,
                         AUTO_MIN_FRAMES_CACHED)[0].backend == "onnxruntime"
    # an OpenVINO precision asks for OpenVINO
    assert choose_engine(SessionConfig(backend="auto", ov_precision="bf16"), manifest, 20)[0].backend == "openvino"


def test_onnxruntime_keeps_its_optimised_graphs(small_model, small_synth, tmp_path, monkeypatch):
    """The optimiser's output is saved per stage and loaded as is the next time (the same numbers,
    the same trajectory); a damaged entry is optimised afresh, not an error."""
    from d3lvo_deploy.backends import ort_cache_file
    from d3lvo_deploy.odometry import Odometry

    monkeypatch.setenv("D3LVO_CACHE", str(tmp_path / "cache"))
    _, onnx_dir = small_model
    seq = KittiSequence.open(small_synth)

    def trajectory(model):
        odo = Odometry(onnx_dir, seq.calib, model=model)
        return np.stack([odo.step(seq.image(i), seq.scan(i)) for i in range(len(seq))])

    sc = SessionConfig(backend="onnxruntime", threads=1)
    first = StageModel(onnx_dir, sc)
    # the flow+pose entry as onnxruntime opens it: its own graph's hash keys the cache
    files = {st: ort_cache_file(sc, st, for_engine(e, "onnxruntime")) for st, e in first.manifest["stages"].items()}
    assert files["flowpose"].name.startswith(f"flowpose-{first.manifest['stages']['flowpose']['onnxruntime']['sha256'][:24]}")
    assert all(f is not None and f.is_file() for f in files.values()), files
    stamps = {st: f.stat().st_mtime_ns for st, f in files.items()}
    second = StageModel(onnx_dir, sc)
    assert {st: f.stat().st_mtime_ns for st, f in files.items()} == stamps  # read, not rewritten
    np.testing.assert_array_equal(trajectory(first), trajectory(second))
    rgb = np.random.default_rng(0).normal(size=(1, 3, first.height, first.width)).astype(np.float32)
    inv = np.zeros((1, 1, first.height, first.width), np.float32)
    np.testing.assert_array_equal(first.complete(rgb, inv), second.complete(rgb, inv))
    files["completion"].write_bytes(b"not an onnx file")
    third = StageModel(onnx_dir, sc)
    np.testing.assert_array_equal(third.complete(rgb, inv), first.complete(rgb, inv))
    assert files["completion"].stat().st_size > 1000  # rewritten from the optimiser
    # no cache for another optimisation level: the optimiser's output is what that level asks for
    assert ort_cache_file(SessionConfig(optimization="basic"), "completion", first.manifest["stages"]["completion"]) is None


@needs_openvino
def test_every_stage_runs_on_the_threads_asked_for(scan_judge_model):
    """--threads is every stage's thread count on both engines, the point solver's flow+pose too
    (two threads measured faster than one for that stage on OpenVINO on an AMD EPYC,
    docs/performance.md). With the classical solve beside (a model with that stage, as the bundled
    one, on two threads), that solve runs on one thread (unpinned on OpenVINO, so that it takes the
    core the others leave) and completion (and on onnxruntime encoder) on one fewer."""
    model_dir = scan_judge_model[1]
    want = {True: {"completion": (1, 1), "encoder": (1, 2), "classical": (1, 1), "flowpose_weighted": (2, 2)},
            False: {"completion": (2, 2), "encoder": (2, 2), "flowpose": (2, 2)}}  # (onnxruntime, OpenVINO)
    for beside, threads in want.items():
        ort_m = StageModel(model_dir, SessionConfig(backend="onnxruntime", threads=2, classical_beside=beside))
        ov_m = StageModel(model_dir, SessionConfig(backend="openvino", threads=2, classical_beside=beside))
        assert ov_m.point_solver and set(ov_m.sessions) == set(ort_m.sessions) == set(threads)
        for name, (n_ort, n_ov) in threads.items():
            assert int(ov_m.sessions[name].compiled.get_property("INFERENCE_NUM_THREADS")) == n_ov, name
            assert ort_m.sessions[name].sess.get_session_options().intra_op_num_threads == n_ort, name
        if beside:
            assert ov_m.sessions["classical"].compiled.get_property("ENABLE_CPU_PINNING") is False


def test_threads_0_reads_omp_num_threads(small_model, monkeypatch):
    """--threads 0 (the default) takes OMP_NUM_THREADS where set, as torch does, and leaves the
    count to the engine where not (onnxruntime's 0); a number asked for wins over the variable."""
    _, onnx_dir = small_model

    def ort_threads(sc: SessionConfig) -> int:
        return StageModel(onnx_dir, sc).sessions["encoder"].sess.get_session_options().intra_op_num_threads

    from d3lvo_deploy.backends import ort_cache_file

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert ort_threads(SessionConfig(backend="onnxruntime")) == 1
    assert ort_threads(SessionConfig(backend="onnxruntime", threads=2)) == 2
    if importlib.util.find_spec("openvino"):
        ov_m = StageModel(onnx_dir, SessionConfig(backend="openvino"))
        assert int(ov_m.sessions["encoder"].compiled.get_property("INFERENCE_NUM_THREADS")) == 1
    # the optimised graph kept for one count is not loaded for another
    stage = {"sha256": "ab" * 32}
    one = ort_cache_file(SessionConfig(), "encoder", stage)
    monkeypatch.setenv("OMP_NUM_THREADS", "3,1")  # OpenMP's list form: the outer level's count
    assert SessionConfig().engine_threads == 3 and ort_cache_file(SessionConfig(), "encoder", stage) != one
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert ort_threads(SessionConfig(backend="onnxruntime")) == 0


def test_run_names_threads_taken_from_omp_num_threads(small_model, small_synth, tmp_path, monkeypatch):
    """A thread count the command line did not give is said, with where it came from."""
    _, onnx_dir = small_model
    args = ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--backend", "onnxruntime"]
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    r = runner.invoke(app, [*args, "--out", str(tmp_path / "a.txt")])
    assert r.exit_code == 0 and "1 thread from OMP_NUM_THREADS" in r.output, r.output
    r = runner.invoke(app, [*args, "--threads", "2", "--out", str(tmp_path / "b.txt")])
    assert r.exit_code == 0 and "OMP_NUM_THREADS" not in r.output, r.output


def test_onnxruntime_threads_do_not_spin_between_runs(small_model):
    """The pool threads spin between the ops of a run (SessionConfig.spinning) but stop when it
    returns: numpy's projection between two stages must have the cores. Measured as this process's
    CPU time while it sleeps after a run: onnxruntime's plain spinning burns ~45 ms of CPU per 100 ms
    idle on 2 threads, a sleeping pool ~0.1 ms."""
    import time

    _, onnx_dir = small_model
    m = StageModel(onnx_dir, SessionConfig(backend="onnxruntime", threads=2))
    assert SessionConfig().spinning
    feeds = {name: np.zeros(shape, np.float32) for name, shape in m.sessions["encoder"].inputs}
    idle = []
    for _ in range(3):
        m.run("encoder", feeds)
        t = time.process_time()
        time.sleep(0.2)
        idle.append(time.process_time() - t)
    assert min(idle) < 0.02, f"CPU seconds while idle after a run: {idle}"


def test_two_cores_solve_the_classical_mode_beside_completion_and_encoder():
    """With two threads or more and a folder that has the classical stage, a run opens it (one
    thread) and the flow+pose graph that takes its pose instead of the batched one, and the stages
    it runs beside one thread short (onnxruntime: completion and encoder; OpenVINO: completion);
    with one thread, the switch off, a three-deep pipeline (whose reader takes the second core for
    completion and encoder) or a folder without the stage, the batched graph on the run's threads."""
    from d3lvo_deploy.backends import stage_configs

    stages = dict.fromkeys(["completion", "encoder", "flowpose", "classical", "flowpose_weighted"])
    threads = lambda configs: {n: c.engine_threads for n, c in configs.items()}  # noqa: E731
    assert threads(stage_configs(stages, SessionConfig(threads=2))) == {
        "completion": 1, "encoder": 1, "classical": 1, "flowpose_weighted": 2}
    # OpenVINO: completion alone one thread short
    assert threads(stage_configs(stages, SessionConfig(threads=2, backend="openvino"))) == {
        "completion": 1, "encoder": 2, "classical": 1, "flowpose_weighted": 2}
    assert threads(stage_configs(stages, SessionConfig(threads=4))) == {
        "completion": 3, "encoder": 3, "classical": 1, "flowpose_weighted": 4}
    # two deep, the flow+pose graph one thread short, beside the reader
    assert threads(stage_configs(stages, SessionConfig(threads=2).pipelined(2))) == {
        "completion": 1, "encoder": 1, "classical": 1, "flowpose_weighted": 1}
    for sc in (SessionConfig(threads=1), SessionConfig(threads=2, classical_beside=False),
               SessionConfig(threads=2).pipelined(3)):
        assert list(stage_configs(stages, sc)) == ["completion", "encoder", "flowpose"]
    batched = dict.fromkeys(["completion", "encoder", "flowpose"])
    assert threads(stage_configs(batched, SessionConfig(threads=2))) == {"completion": 2, "encoder": 2, "flowpose": 2}


def test_a_pipelined_run_gives_the_flowpose_stage_one_thread_fewer(small_model, small_synth, tmp_path):
    """Pipelined, the reader thread works beside the flow+pose stage: that stage opens with one
    thread fewer than the cores given, so that the reader has one of its own. Three deep (on
    onnxruntime, without pictures) the reader also runs completion and encoder, on that one
    thread; one frame at a time every stage has them all. One thread leaves nothing to split."""
    sc = SessionConfig(threads=2)
    assert sc.pipelined().for_stage("flowpose").engine_threads == 1
    assert sc.pipelined().for_stage("encoder").engine_threads == 2
    assert sc.pipelined(3).for_stage("encoder").engine_threads == 1
    assert SessionConfig(threads=1).pipelined() == SessionConfig(threads=1)
    assert SessionConfig(threads=4).pipelined().pipelined().for_stage("flowpose").engine_threads == 3
    _, onnx_dir = small_model
    seq = KittiSequence.open(small_synth)
    cases = (("three deep", True, None, 3, 1, 1), ("two deep, pictures", True, tmp_path / "viz", 2, 1, 2),
             ("one at a time", False, None, 1, 2, 2))
    for name, pipeline, viz, depth, solver_threads, other_threads in cases:
        rc = RunConfig(out=tmp_path / f"{depth}.txt", pipeline=pipeline, viz_dir=viz)
        plan = prepare_run(seq, onnx_dir, rc, SessionConfig(threads=2, backend="onnxruntime"))
        assert plan.depth == depth, name
        threads = {n: s.sess.get_session_options().intra_op_num_threads for n, s in plan.odo.model.sessions.items()}
        assert threads.pop("flowpose") == solver_threads, name
        assert threads and set(threads.values()) == {other_threads}, name
        # a frame's CPU half on two threads only where no reader runs it beside the network
        assert plan.odo.prepare_threads == (1 if pipeline else 2), name
    assert SessionConfig(threads=1).preparing_threads == 1
    assert SessionConfig(threads=2, prepare_threads=1).preparing_threads == 1  # `d3lvo bench --prepare-threads`
    # a stage's settings are what opens its session: two deep, completion and encoder open as one at a time
    assert SessionConfig(threads=2).pipelined().for_stage("encoder") == SessionConfig(threads=2).for_stage("encoder")
    # sessions opened by the caller cannot be split: two deep; the direct tracker prepares nothing apart
    from d3lvo_deploy.direct import DirectOdometry

    given = StageModel(onnx_dir, SessionConfig(threads=2, backend="onnxruntime"))
    plan = prepare_run(seq, onnx_dir, RunConfig(out=tmp_path / "given.txt", pipeline=True),
                       SessionConfig(threads=2, backend="onnxruntime"), model=given)
    assert (plan.depth, plan.sc) == (2, None)
    plan = prepare_run(seq, None, RunConfig(out=tmp_path / "direct.txt", pipeline=True), SessionConfig(threads=2),
                       odometry=DirectOdometry(seq.calib))
    assert plan.depth == 1


def test_the_pipelined_split_counts_physical_cores(tmp_path, monkeypatch):
    """Left to themselves the engines take one thread per physical core: on 2 cores with two
    hyperthreads each (CPUs 0-3, siblings 0,2 and 1,3) the flow+pose stage gets 1 thread, not 3."""
    from d3lvo_deploy import backends

    for cpu, siblings in enumerate(("0,2", "1,3", "0,2", "1,3")):
        (tmp_path / f"cpu{cpu}" / "topology").mkdir(parents=True)
        (tmp_path / f"cpu{cpu}" / "topology" / "thread_siblings_list").write_text(siblings + "\n")
    monkeypatch.setattr(backends.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    assert backends.usable_cores(str(tmp_path)) == 2
    monkeypatch.setattr(backends, "usable_cores", lambda: 2)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert SessionConfig().pipelined().for_stage("flowpose").engine_threads == 1
