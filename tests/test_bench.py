"""`d3lvo bench` runs and its numbers are consistent with each other (no timing thresholds)."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from d3lvo_deploy.bench import StageTimes, bench_onnx
from d3lvo_deploy.onnx_model import SessionConfig
from d3lvo_deploy.sequence import KittiSequence

runner = CliRunner()


def test_total_is_the_frame_time_measured_outside(small_model, small_synth, monkeypatch):
    """A frame's total against a clock the test holds around each `Odometry.step` call: the stages
    lie inside the call, so the total never exceeds it, and they cover nearly all of it (a stage
    left out of the total, or timed twice, breaks one side)."""
    import time

    from d3lvo_deploy.odometry import Odometry

    walls = []
    step = Odometry.step

    def timed_step(self, image, points):
        t0 = time.perf_counter()
        pose = step(self, image, points)
        walls.append((time.perf_counter() - t0) * 1000)
        return pose

    monkeypatch.setattr(Odometry, "step", timed_step)
    _, onnx_dir = small_model
    t = bench_onnx(onnx_dir, KittiSequence.open(small_synth), SessionConfig(threads=1), runs=4, warmup=1)
    s = t.samples
    assert len(s["total"]) == 4 and len(walls) == 5
    for total, wall in zip(s["total"], walls[1:]):
        assert total <= wall + 1e-3, (total, wall)
    assert sum(s["total"]) >= 0.8 * sum(walls[1:]), (s["total"], walls)
    summ = t.summary()
    for k, v in summ.items():
        assert v["min"] <= v["median"] <= v["p90"] <= v["max"]


def test_stage_times_summary_by_hand():
    """Skewed samples, so median, mean, p90 and max all differ: encoder 1, 2, 4, 8, 100 ms and
    flowpose 10 ms each. By hand: median 4; p90 by linear interpolation between the 4th (8) and
    5th (100) sorted values at rank 0.9 * 4 = 3.6: 8 + 0.6 * 92 = 63.2; the totals are 11, 12,
    14, 18, 110 (median 14, max 110, min 11)."""
    t = StageTimes()
    for enc in (8.0, 1.0, 100.0, 2.0, 4.0):  # not in order
        t.add({"encoder": enc, "flowpose": 10.0})
    s = t.summary()
    assert (s["encoder"]["median"], s["encoder"]["min"], s["encoder"]["max"]) == (4.0, 1.0, 100.0)
    assert abs(s["encoder"]["p90"] - 63.2) < 1e-9
    assert (s["total"]["median"], s["total"]["min"], s["total"]["max"]) == (14.0, 11.0, 110.0)
    assert abs(s["total"]["p90"] - (18.0 + 0.6 * 92.0)) < 1e-9
    assert "completion" not in s  # a stage never timed is not reported as 0


def test_cli_bench_json(small_model, small_synth):
    ck, onnx_dir = small_model
    r = runner.invoke(app, ["bench", "--onnx", str(onnx_dir), "--seq-dir", str(small_synth), "--runs", "3",
                            "--threads", "1", "--json", "--backend", "onnxruntime", "--prepare-threads", "2"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["prepare_threads"] == 2  # asked for, though one engine thread alone would give 1
    for key in ("total_ms_median", "ort_over_torch", "rss_mb", "fps", "stages_ms", "torch_stages_ms"):
        assert key in d
    # the total's median is the median of the per-frame sums, not the sum of the stage medians
    totals = d["stages_ms"]["total"]
    assert totals["min"] <= totals["median"] <= totals["max"] and d["total_ms_median"] == totals["median"]
    assert d["rss_mb"] > 10 and d["ort_over_torch"] > 0
    assert set(d["stages_ms"]) >= {"project", "completion", "encoder", "flowpose", "total"}


def test_cli_bench_against_another_folder_times_both_in_turns(small_model, small_synth, tmp_path):
    """--against times a second export on the same engine and frames, taking turns with the model;
    a folder that is not an export is refused by name."""
    ck, onnx_dir = small_model
    args = ["bench", "--onnx", str(onnx_dir), "--seq-dir", str(small_synth), "--runs", "2", "--threads", "1",
            "--no-torch", "--backend", "onnxruntime"]
    r = runner.invoke(app, args + ["--json", "--against", str(onnx_dir)])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    other = d["against"]["backends"]["onnxruntime"]["stages_ms"]
    assert d["against"]["model"] == str(onnx_dir)
    assert set(other) == set(d["stages_ms"])
    assert other["total"]["min"] <= other["total"]["median"] <= other["total"]["max"]
    r = runner.invoke(app, args + ["--against", str(tmp_path)])
    assert r.exit_code != 0 and str(tmp_path) in r.output and "Traceback" not in r.output


def test_cli_bench_from_checkpoint(small_synth, tmp_path):
    """`--ckpt --precision fp16`: exported, converted, then timed, and the report's first line and
    its table title say so. On the MLP pose head, the cheapest head to export (the bundled
    model's point solver is timed through its shipped graphs by the other bench tests)."""
    from conftest import make_checkpoint

    ck = make_checkpoint(tmp_path / "ck.pt", pose_head="mlp")
    r = runner.invoke(app, ["bench", "--ckpt", str(ck), "--precision", "fp16", "--seq-dir", str(small_synth),
                            "--runs", "2", "--no-torch", "--backend", "onnxruntime"])
    assert r.exit_code == 0, r.output
    assert r.output.splitlines()[0] == f"model: {ck}, exported"  # so a figure is never read as another model's
    assert "2 frames (fp16)" in r.output and "frames/s" in r.output


def test_cli_bench_default_network_at_another_size(small_synth):
    """--height/--width without --ckpt: the default network (D3LVOConfig()) exported at that size.
    The JSON says which."""
    r = runner.invoke(app, ["bench", "--height", "64", "--width", "256", "--seq-dir", str(small_synth), "--runs", "1",
                            "--threads", "1", "--no-torch", "--json", "--backend", "onnxruntime"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["size"] == "256x64" and d["timed"].startswith("the default network")
    assert d["precision"] == "fp32"
    from models.config import D3LVOConfig

    assert d["flow_levels"] == list(D3LVOConfig().flow_levels)


def test_cli_bench_size_needs_both_and_no_fixed_folder(small_model):
    _, onnx_dir = small_model
    r = runner.invoke(app, ["bench", "--height", "64"])
    assert r.exit_code != 0 and "--height and --width together" in r.output
    r = runner.invoke(app, ["bench", "--onnx", str(onnx_dir), "--height", "64", "--width", "256"])
    assert r.exit_code != 0 and "fixed size" in r.output
    # --precision goes with --height/--width (the default network exported at that precision):
    # accepted, so the next check, of --threads, is the one that stops this command
    r = runner.invoke(app, ["bench", "--height", "64", "--width", "256", "--precision", "fp16", "--threads", "-1"])
    assert r.exit_code != 0 and "--threads" in r.output and "--precision" not in r.output, r.output
    for args, words in ((["--height", "0", "--width", "0"], "input 0x0 is too small: at least 32x32"),
                        (["--height", "-16", "--width", "64"], "input 64x-16 is too small"),
                        (["--backend", "onnxruntime", "--ov-precision", "bf16"], "--ov-precision applies to OpenVINO"),
                        (["--seq-dir", "nowhere"], "nowhere: sequence folder not found"),
                        (["--profile", __file__], "is a file; --profile names the folder for the profiles"),
                        (["--onnx", str(onnx_dir), "--ckpt", str(onnx_dir.parent / "ck.pt")], "not both")):
        r = runner.invoke(app, ["bench", *args])
        assert r.exit_code == 1 and words in r.output and "Traceback" not in r.output, (args, r.output)


def test_cli_bench_refuses_a_backend_list_without_an_engine():
    """An unknown engine, or a --backend that names none, is one line before anything is exported
    or timed (an empty list would otherwise reach the timing with nothing to time)."""
    for value, shown in (("foo", "'foo'"), (",", "','"), ("onnxruntime,bar", "'bar'")):
        r = runner.invoke(app, ["bench", "--height", "64", "--width", "256", "--backend", value])
        assert r.exit_code == 1 and "--backend takes onnxruntime, openvino" in r.output and shown in r.output, r.output
        assert "Traceback" not in r.output


def test_conv_bench_finds_every_conv_once():
    """Each Conv2d of the network runs once per frame pair (complete, encode, flow_pose), except the
    Gauss-Newton head's feature projections, which run on both frames: the recorded calls add up
    to the model's Conv2d count plus one per flow level, and the first RGB conv has its known shape."""
    import torch

    from export.conv_bench import ConvShape, conv_layers
    from models.config import D3LVOConfig
    from models.d3lvo import D3LVO

    cfg = D3LVOConfig(height=64, width=128)
    layers = conv_layers(cfg)
    n_modules = sum(isinstance(m, torch.nn.Conv2d) for m in D3LVO(cfg).modules())
    assert sum(layers.values()) == n_modules + len(cfg.flow_levels)
    first_rgb = ConvShape(3, cfg.rgb_widths[0], 3, 2, 1, 1, 64, 128)
    assert layers[first_rgb] == 1
    assert first_rgb.gmac == 3 * cfg.rgb_widths[0] * 9 * 32 * 64 / 1e9


def test_conv_bench_table_totals(capsys):
    from export.conv_bench import main

    main(["--height", "32", "--width", "64", "--threads", "1", "--runs", "1"])
    lines = capsys.readouterr().out.splitlines()
    rows = [ln.split() for ln in lines[2:-1]]
    total = lines[-1].split()
    calls = sum(int(r[4]) for r in rows)  # label is 4 tokens: "3->16 3x3/2 at 64x32"
    assert total[2] == str(calls)
    assert abs(sum(float(r[6]) for r in rows) - float(total[4])) < 0.05 * len(rows)


def test_cli_bench_precision_errors(small_model):
    _, onnx_dir = small_model
    r = runner.invoke(app, ["bench", "--onnx", str(onnx_dir), "--precision", "int8"])
    assert r.exit_code == 1 and "fixed precision" in r.output
    r = runner.invoke(app, ["bench", "--precision", "int8"])
    assert r.exit_code == 1 and "needs --ckpt or --height/--width" in r.output
    r = runner.invoke(app, ["bench", "--height", "64", "--width", "256", "--precision", "int4"])
    assert r.exit_code == 1 and "fp32, fp16 or int8" in r.output
    r = runner.invoke(app, ["bench", "--onnx", str(onnx_dir), "--prepare-threads", "3"])
    assert r.exit_code == 1 and "--prepare-threads must be 1 or 2" in r.output


def test_engines_take_turns_in_blocks_each_on_its_own_consecutive_frames(small_model, small_synth, monkeypatch):
    """Two engines timed together are warmed up one after the other, then alternate 2 frames at a
    time, each stepping the frames 0, 1, 2, ... of its own stream, and each gets exactly `runs`
    samples."""
    from d3lvo_deploy.bench import bench_engines
    from d3lvo_deploy.odometry import Odometry

    seq = KittiSequence.open(small_synth)
    order = []
    step = Odometry.step

    def recording_step(self, image, points):
        order.append((id(self), int(np.asarray(image).sum())))
        return step(self, image, points)

    monkeypatch.setattr(Odometry, "step", recording_step)
    _, onnx_dir = small_model
    scs = [SessionConfig(threads=1), SessionConfig(threads=1)]
    times = bench_engines(onnx_dir, seq, scs, runs=4, warmup=1, block=2)
    assert [len(t.samples["total"]) for t in times] == [4, 4]
    stepped = [o for o, _ in order[:10]]  # the timed loop, before the pipelined one
    a, b = stepped[0], stepped[1]
    assert a != b and stepped == [a, b, a, a, b, b, a, a, b, b]
    n = min(len(seq), 10)
    sums = [int(np.asarray(seq.image(i)).sum()) for i in range(n)]
    for engine in (a, b):
        assert [s for o, s in order[:10] if o == engine] == [sums[k % n] for k in range(5)]


def test_a_stage_beside_the_others_is_timed_but_not_added_to_the_frame():
    """The classical solve runs on another thread while completion and encoder do: its row is its
    own time, the frame's total the stages the frame waited for (the flow+pose stage's time holds
    any wait for the solve), and the table's GFLOP those of the graphs the frame ran."""
    from cli.bench_cmd import _row_gflops
    from d3lvo_deploy.bench import BESIDE_ROW, StageTimes

    t = StageTimes()
    t.add({"project": 1.0, "completion": 2.0, "encoder": 3.0, BESIDE_ROW: 4.5, "flowpose": 7.0})
    assert t.samples["total"] == [13.0] and t.samples[BESIDE_ROW] == [4.5]
    gf = {"completion": 1.0, "encoder": 2.0, "flowpose": 4.0, "classical": 0.5, "flowpose_weighted": 3.0}
    assert _row_gflops(gf, beside=True) == {"completion": 1.0, "encoder": 2.0, "flowpose": 3.0, BESIDE_ROW: 0.5,
                                             "total": 6.5}
    assert _row_gflops(gf, beside=False) == {"completion": 1.0, "encoder": 2.0, "flowpose": 4.0, "total": 7.0}


def test_pipelined_fps_steps_every_frame_in_order_once():
    """The pipelined timing prepares frame k+1 while frame k steps: every frame, in order, each
    prepared once (one more is prepared ahead and dropped)."""
    from d3lvo_deploy.bench import pipelined_fps

    class Recorder:
        def __init__(self):
            self.prepared, self.stepped = [], []

        def prepare(self, image, points, threads=None):
            assert threads == 1  # the reader thread has one core beside the network, as a run's
            self.prepared.append(image)
            return image

        def step_prepared(self, frame, on_encoded=None):
            self.stepped.append(frame)
            if on_encoded is not None:
                on_encoded()

        def encode_timed(self, frame):
            return ("encoded", frame), {"encoder": 0.0}

        def step_encoded(self, enc, times):
            assert enc[0] == "encoded" and times == {"encoder": 0.0}
            self.stepped.append(enc[1])

    for depth in (2, 3):  # three-deep: each frame also encoded ahead, once
        rec = Recorder()
        frames = [(k, None) for k in range(4)]
        fps = pipelined_fps(rec, frames, 6, depth)
        assert rec.stepped == [0, 1, 2, 3, 0, 1]
        assert rec.prepared == [0, 1, 2, 3, 0, 1, 2]
        assert fps > 0


def test_torch_side_times_the_point_solver_model(small_synth):
    """The bundled model's kind (`pose_head="points"`): torch's flow+pose takes the solver's points
    and image pyramids and frame t's depths, as the ONNX graph does, instead of failing on them."""
    pytest.importorskip("torch")
    from d3lvo_deploy.bench import take_turns, warm_up
    from models.bench_torch import TorchStream
    from models.config import D3LVOConfig

    cfg = D3LVOConfig.small(pose_head="points", pt_iters=(2, 2, 2))
    stream = TorchStream(cfg, KittiSequence.open(small_synth), threads=1)
    warm_up([stream], 1)
    t = take_turns([stream], 2)[0].summary()
    assert set(t) >= {"completion", "encoder", "flowpose", "total"}
    assert t["flowpose"]["min"] > 0 and t["total"]["median"] >= t["flowpose"]["median"]


def test_cli_bench_times_torch_in_turns_with_the_engines(small_model, small_synth, monkeypatch):
    """torch is timed in the same turns as the engines (5 frames each), not after them, so that a
    VM's drift reaches both sides of the engine/torch ratio alike: after the warm-ups (3 engine
    frames, 2 torch frames), 7 timed frames each run as engine x5, torch x5, engine x2, torch x2."""
    pytest.importorskip("torch")
    from d3lvo_deploy.odometry import Odometry
    from models.bench_torch import TorchStream

    order = []
    step, call = Odometry.step, TorchStream.__call__

    def engine_step(self, image, points):
        order.append("engine")
        return step(self, image, points)

    def torch_step(self):
        order.append("torch")
        return call(self)

    monkeypatch.setattr(Odometry, "step", engine_step)
    monkeypatch.setattr(TorchStream, "__call__", torch_step)
    _, onnx_dir = small_model
    r = runner.invoke(app, ["bench", "--onnx", str(onnx_dir), "--seq-dir", str(small_synth), "--runs", "7",
                            "--threads", "1", "--json", "--backend", "onnxruntime"])
    assert r.exit_code == 0, r.output
    timed = order[:3 + 2 + 14]  # the pipelined timing steps the engine afterwards
    assert timed == ["engine"] * 3 + ["torch"] * 2 + ["engine"] * 5 + ["torch"] * 5 + ["engine"] * 2 + ["torch"] * 2
    d = json.loads(r.stdout)
    assert d["ort_over_torch"] > 0 and set(d["torch_stages_ms"]) >= {"completion", "encoder", "flowpose"}


def test_cli_bench_refuses_a_single_frame(tmp_path):
    """One frame would be timed against itself: no motion, a solver that stops at once, times too
    good to be true."""
    import shutil

    from conftest import ROOT

    one = tmp_path / "one"
    shutil.copytree(ROOT / "tests" / "data" / "tiny_seq", one)
    for sub, ext in (("image_2", ".png"), ("velodyne", ".bin")):
        for k in (1, 2):
            (one / sub / f"{k:06d}{ext}").unlink()
    for name in ("times.txt", "poses.txt"):
        (one / name).write_text((one / name).read_text().splitlines()[0] + "\n")
    r = runner.invoke(app, ["bench", "--seq-dir", str(one), "--runs", "1", "--no-torch"])
    assert r.exit_code == 1 and "bench needs at least 2 frames" in r.output and str(one) in r.output, r.output
