"""`d3lvo bench`: per-stage latency, frames/s and peak memory of the ONNX pipeline vs torch eager."""

from __future__ import annotations

import json
import tempfile
from dataclasses import replace
from pathlib import Path

import typer
from rich.table import Table

from d3lvo_deploy.errors import D3LVOInputError

from .common import console, friendly_errors, note_oversubscribed, out


def _bench_frames(tmp: Path) -> Path:
    """Real KITTI frames when ../shared/data is present, else a synthetic full-size sequence."""
    from d3lvo_deploy.bundled import find_real_frames

    real = find_real_frames()
    if real is not None:
        return real
    from d3lvo_deploy.synth.generator import SynthConfig, generate

    return generate(tmp / "bench_seq", SynthConfig(frames=6, seed=321))


def _default_network_checkpoint(tmp: Path, height: int, width: int) -> Path:
    """Speed does not depend on weight values, so the default network is timed with seeded random ones."""
    import torch

    from models.checkpoint import save_checkpoint
    from models.config import D3LVOConfig
    from models.d3lvo import D3LVO

    try:
        cfg = D3LVOConfig(height=height, width=width)
    except ValueError as e:
        raise D3LVOInputError(None, str(e)) from None
    torch.manual_seed(0)
    path = tmp / "default_network.pt"
    save_checkpoint(path, D3LVO(cfg), cfg)
    return path


def _stage_gflops(onnx: Path, manifest: dict) -> dict[str, float]:
    """GFLOP per stage from the manifest (written by `d3lvo export`), else counted when onnx is here."""
    out = {}
    for name, st in manifest["stages"].items():
        if "gflops" in st:
            out[name] = float(st["gflops"])
            continue
        try:
            from export.flops import graph_flops
        except ImportError:
            continue
        out[name] = graph_flops(onnx / st["file"]) / 1e9
    return out


def _row_gflops(stage_gflops: dict[str, float], beside: bool) -> dict[str, float]:
    """The GFLOP of each row of the bench's table from the manifest's stages: with the classical
    solve timed beside (`BESIDE_ROW`), its graph's and the flow+pose graph that takes its pose;
    the total, of the graphs a frame runs."""
    from d3lvo_deploy.backends import BESIDE_STAGE, WEIGHTED_STAGE
    from d3lvo_deploy.bench import BESIDE_ROW

    graphs = {"completion": "completion", "encoder": "encoder", "flowpose": WEIGHTED_STAGE if beside else "flowpose"}
    if beside:
        graphs[BESIDE_ROW] = BESIDE_STAGE
    rows = {row: stage_gflops[g] for row, g in graphs.items() if g in stage_gflops}
    if rows:
        rows["total"] = sum(rows.values())
    return rows


def _torch_streams(manifest: dict, seq, threads: int, eager: bool, compile: bool, frames: list) -> dict:
    """torch eager and torch.compile on the exported model's config, warmed up (compiled), ready to
    take turns with the engines; none when torch is not installed."""
    if not (eager or compile):
        return {}
    try:
        from models.bench_torch import TorchStream
        from models.config import D3LVOConfig
    except ImportError:
        console.print("torch is not installed: no torch comparison", highlight=False)
        return {}
    from d3lvo_deploy.bench import warm_up

    cfg = D3LVOConfig.from_dict(manifest["model_config"])
    streams = {}
    if eager:
        streams["torch eager"] = TorchStream(cfg, seq, threads, frames=frames)
    if compile:
        streams["torch.compile"] = TorchStream(cfg, seq, threads, compile=True, frames=frames)
    with console.status("warming up torch" + (" (torch.compile compiles: about a minute on 2 cores)" if compile else "")):
        for stream in streams.values():
            warm_up([stream], stream.warmup)
    return streams


@friendly_errors
def bench_command(
    onnx: Path | None = typer.Option(None, "--onnx", help="Exported model folder (default: the bundled model)."),
    ckpt: Path | None = typer.Option(None, "--ckpt", help="Or a checkpoint: exported to a temporary folder first."),
    height: int | None = typer.Option(None, "--height", help="Export --ckpt at this height; without --ckpt, time the default network (D3LVOConfig()) at this size."),
    width: int | None = typer.Option(None, "--width", help="... and this width (e.g. --height 352 --width 1216)."),
    threads: int = typer.Option(2, "--threads", help="Threads for every engine and torch."),
    classical_beside: bool = typer.Option(True, "--classical-beside/--no-classical-beside", help="With a model that "
                                          "has the classical stage (the bundled one): solve the classical mode beside "
                                          "completion and encoder (two cores or more), or in the flow+pose graph."),
    prepare_threads: int = typer.Option(0, "--prepare-threads", help="Threads of each frame's CPU half (the project "
                                        "row): 1 or 2 (default: as `d3lvo run` decides, 2 from two cores up)."),
    runs: int = typer.Option(20, "--runs", help="Timed frames after warm-up."),
    seq_dir: Path | None = typer.Option(None, "--seq-dir", help="Frames to run on (default: real frames, else synthetic)."),
    backend: str | None = typer.Option(None, "--backend", help="Engines to time, comma-separated: onnxruntime, "
                                       "openvino (default: every one installed)."),
    ov_precision: str = typer.Option("f32", "--ov-precision", help="OpenVINO's inference precision: f32 | bf16."),
    torch_compare: bool = typer.Option(True, "--torch/--no-torch", help="Also time torch eager on the same stages."),
    torch_compile: bool = typer.Option(False, "--torch-compile", help="Also time torch.compile (inductor); compiles "
                                       "each stage first, about a minute on 2 cores."),
    as_json: bool = typer.Option(False, "--json", help="Print the numbers as JSON."),
    profile: Path | None = typer.Option(None, "--profile", help="Write onnxruntime profiles here and list the top ops."),
    precision: str = typer.Option("fp32", "--precision", help="With --ckpt or --height/--width: export at fp32 | fp16 | "
                                  "int8 first (INT8 calibrated as `d3lvo export` does). Torch stays FP32."),
    against: Path | None = typer.Option(None, "--against", help="Another exported folder of the same size, timed on "
                                        "every engine taking turns with the model: two exports compared under the "
                                        "same drift of the machine's speed."),
) -> None:
    """Per stage and engine: median/p90/max latency, GFLOP/s against this CPU's GEMM peak, frames/s,
    peak RSS, and the speed-up over torch eager (and torch.compile); the CPU and its vector
    extensions head the output, so a figure is never quoted without its machine.

    Example: d3lvo bench --runs 30 --no-torch   (the bundled model; --height 352 --width 1216: the paper's size)
    """
    from d3lvo_deploy.backends import BACKENDS, SessionConfig, available_backends
    from d3lvo_deploy.bench import (BESIDE_ROW, ENGINE_WARMUP, TURN_FRAMES, EngineStream, bench_frames, peak_rss_mb,
                                    take_turns, warm_up)
    from d3lvo_deploy.bundled import find_real_frames
    from d3lvo_deploy.cpu import cpu_info, gemm_peak_gflops
    from d3lvo_deploy.manifest import load_manifest
    from d3lvo_deploy.sequence import KittiSequence

    if runs < 1:
        raise D3LVOInputError(None, "--runs must be at least 1")
    note_oversubscribed(threads)
    if prepare_threads not in (0, 1, 2):
        raise D3LVOInputError(None, f"--prepare-threads must be 1 or 2, not {prepare_threads}")
    if (height is None) != (width is None):
        raise D3LVOInputError(None, "give --height and --width together")
    if height is not None:
        from models.config import input_size_problem

        problem = input_size_problem(height, width)
        if problem:
            raise D3LVOInputError(None, f"--height {height} --width {width}: {problem}")
    if ckpt is not None and onnx is not None:
        raise D3LVOInputError(None, "give --onnx (an exported folder) or --ckpt (a checkpoint, exported first), not both")
    if height is not None and onnx is not None:
        raise D3LVOInputError(onnx, "an exported folder has a fixed size; use --ckpt (or neither) with --height/--width")
    if precision not in ("fp32", "fp16", "int8"):
        raise D3LVOInputError(None, f"--precision must be fp32, fp16 or int8, not {precision!r}")
    if precision != "fp32" and onnx is not None:
        raise D3LVOInputError(onnx, "an exported folder has a fixed precision (see its manifest); use --ckpt or "
                                    "--height/--width with --precision")
    default_network = ckpt is None and onnx is None and height is not None
    if precision != "fp32" and ckpt is None and not default_network:
        raise D3LVOInputError(None, "--precision needs --ckpt or --height/--width (the bundled model is fp32)")
    # without --backend, every installed engine, listed after any export: listing imports OpenVINO,
    # whose pybind11 module slows torch's exporter (docs/export-and-parity.md)
    engines = None if backend is None else list(dict.fromkeys(b.strip() for b in backend.split(",") if b.strip()))
    unknown = [] if engines is None else [b for b in engines or [backend] if b not in BACKENDS]
    if unknown:  # an engine we do not know, or a list that names none
        raise D3LVOInputError(None, f"--backend takes {', '.join(BACKENDS)} (comma-separated), not {unknown[0]!r}")
    if ov_precision != "f32" and engines is not None and "openvino" not in engines:
        raise D3LVOInputError(None, "--ov-precision applies to OpenVINO: add openvino to --backend")
    for b in BACKENDS if engines is None else engines:
        SessionConfig(backend=b, ov_precision=ov_precision if b == "openvino" else "f32", threads=threads).check()
    # 0: as `d3lvo run` takes them (OMP_NUM_THREADS where set, else one per physical core); the
    # table and --json say how many that is
    threads = SessionConfig(threads=threads).threads_taken
    if engines is not None and "openvino" in engines:
        from d3lvo_deploy.extras import require

        require("openvino", what="--backend openvino")
    if profile is not None and engines is not None and "onnxruntime" not in engines:
        raise D3LVOInputError(profile, "--profile writes onnxruntime profiles: include --backend onnxruntime")
    if profile is not None:  # before a minute of benching, not at the first session
        from d3lvo_deploy.results import make_output_folder

        make_output_folder(profile, "--profile", "the profiles")
        earlier = set(profile.glob("*.json"))  # an earlier bench's profiles, or other files: not this run's
    if ckpt is not None or default_network or torch_compile:
        from d3lvo_deploy.extras import require

        require("torch", "onnx", what="d3lvo bench with --ckpt, --height/--width or --torch-compile")
    other = None if against is None else load_manifest(against)  # a clear error for a folder that is no export
    if seq_dir is not None:
        from d3lvo_deploy.sequence import KittiSequence

        if len(KittiSequence.open(seq_dir)) < 2:  # a bad folder is one error before an export
            # one frame would be timed against itself: no motion, a solver that stops at once
            raise D3LVOInputError(seq_dir, "bench needs at least 2 frames (it times frame pairs)")
    if seq_dir is None and find_real_frames() is None:
        from d3lvo_deploy.extras import require

        require("embreex", what="d3lvo bench without --seq-dir or ../shared/data (it renders frames)")
    cpu = cpu_info()
    # what is timed, in words: the bench's first line says it, so a figure is never read as another model's
    if default_network:
        what = f"the default network (D3LVOConfig(), random weights) exported at {width}x{height}"
    elif ckpt is not None:
        what = f"{ckpt}, exported" + (f" at {width}x{height}" if height is not None else "")
    elif onnx is not None:
        what = str(onnx)
    else:
        what = "the bundled model (what `d3lvo run` uses by default)"
    with tempfile.TemporaryDirectory(prefix="d3lvo-bench-") as tmpd:
        tmp = Path(tmpd)
        if default_network:
            ckpt = _default_network_checkpoint(tmp, height, width)
        if ckpt is not None:
            from export.onnx_export import ExportConfig, export_checkpoint

            onnx = tmp / "onnx"
            with console.status("exporting the checkpoint"):
                export_checkpoint(ckpt, ExportConfig(out=onnx, height=height, width=width))
            if precision != "fp32":
                from export.quantize import quantize_folder

                from .export_cmd import default_calibration

                with console.status(f"converting to {precision}"):
                    calib = default_calibration(tmp) if precision == "int8" else []
                    quantize_folder(onnx, tmp / f"onnx_{precision}", precision, calib)
                onnx = tmp / f"onnx_{precision}"
        if onnx is None:
            from d3lvo_deploy.bundled import bundled_model_dir

            onnx = bundled_model_dir()
        if engines is None:
            engines = available_backends()
        manifest = load_manifest(onnx)
        if other is not None and (other["input"]["width"], other["input"]["height"]) != (
                manifest["input"]["width"], manifest["input"]["height"]):
            raise D3LVOInputError(against, f"is an export for {other['input']['width']}x{other['input']['height']} "
                                           f"input; --against needs one of the model's "
                                           f"{manifest['input']['width']}x{manifest['input']['height']}")
        gflops = _stage_gflops(onnx, manifest)
        seq = KittiSequence.open(seq_dir or _bench_frames(tmp))
        with console.status("measuring the GEMM peak"):
            peak = gemm_peak_gflops()
        timed: dict[str, dict] = {}
        pipelined: dict[str, float | None] = {}
        top_ops = None
        scs = [SessionConfig(threads=threads, backend=b, ov_precision=ov_precision if b == "openvino" else "f32",
                             profile_dir=str(profile) if profile and b == "onnxruntime" else None,
                             prepare_threads=prepare_threads, classical_beside=classical_beside) for b in engines]
        frames = bench_frames(seq)
        with console.status(f"loading {', '.join(engines)}"):
            streams = {b: EngineStream(onnx, seq, sc, frames) for b, sc in zip(engines, scs)}
            if against is not None:  # no profile of the other folder: the profile lists the model's ops
                streams.update({f"{b} --against": EngineStream(against, seq, replace(sc, profile_dir=None), frames)
                                for b, sc in zip(engines, scs)})
            warm_up(list(streams.values()), ENGINE_WARMUP)
        rss = peak_rss_mb()  # before torch is imported: what a vehicle process needs
        torch_streams = _torch_streams(manifest, seq, threads, torch_compare, torch_compile, frames)
        streams.update(torch_streams)
        turns = f", taking turns {TURN_FRAMES} frames at a time" if len(streams) > 1 else ""
        with console.status(f"timing {', '.join(streams)} ({runs} frames each{turns}, then {runs} pipelined)"):
            times = dict(zip(streams, take_turns(list(streams.values()), runs)))
            for b in engines:
                streams[b].finish(times[b], runs)
                timed[b], pipelined[b] = times[b].summary(), times[b].pipelined_fps
        if profile is not None:
            from d3lvo_deploy.bench import profile_summary

            top_ops = profile_summary(sorted(str(p) for p in set(profile.glob("*.json")) - earlier))
        torch_t = times["torch eager"].summary() if "torch eager" in times else None
        compiled_t = times["torch.compile"].summary() if "torch.compile" in times else None
    net = ("completion", "encoder", "flowpose")
    network_ms = lambda t: sum(t[k]["median"] for k in net if k in t)  # noqa: E731
    best = min(timed, key=lambda b: timed[b]["total"]["median"])
    first = "onnxruntime" if "onnxruntime" in timed else best
    res = {
        "model": str(onnx), "timed": what, "size": f"{manifest['input']['width']}x{manifest['input']['height']}",
        "precision": manifest.get("precision", "fp32"), "flow_levels": manifest["model_config"]["flow_levels"],
        "threads": SessionConfig(threads=threads).engine_threads, "runs": runs, "frames_from": str(seq.root),
        "prepare_threads": scs[0].preparing_threads,
        "ov_precision": ov_precision if "openvino" in engines else None,
        "cpu": {"model": cpu.model, "cores": cpu.logical_cores, "isa": list(cpu.isa)},
        # GFLOP/s of the machine; GFLOP per frame of each exported graph (`stage_gflops`) and of each
        # row the table and `stages_ms` name (`row_gflop`, the graphs that row runs)
        "gemm_peak_gflops": peak, "stage_gflops": gflops,
        "row_gflop": _row_gflops(gflops, any(BESIDE_ROW in t for t in timed.values())),
        "backends": {b: {"stages_ms": t, "total_ms_median": t["total"]["median"], "total_ms_max": t["total"]["max"],
                         "fps": 1000.0 / t["total"]["median"], "pipelined_fps": pipelined.get(b)}
                     for b, t in timed.items()},
        "best_backend": best,
        # the first engine's figures under the keys earlier versions printed
        "stages_ms": timed[first], "total_ms_median": timed[first]["total"]["median"],
        "fps": 1000.0 / timed[first]["total"]["median"], "rss_mb": rss,
    }
    if torch_t is not None:
        res["torch_stages_ms"] = torch_t
        res["ort_over_torch"] = network_ms(torch_t) / network_ms(timed[first])  # above 1: the engine is faster
        res["best_over_torch"] = network_ms(torch_t) / network_ms(timed[best])
    if compiled_t is not None:
        res["torch_compile_stages_ms"] = compiled_t
        res["best_over_torch_compile"] = network_ms(compiled_t) / network_ms(timed[best])
    if top_ops is not None:
        res["top_ops_ms"] = top_ops
    if against is not None:
        res["against"] = {"model": str(against),
                          "backends": {b: {"stages_ms": times[f"{b} --against"].summary()} for b in engines}}
    if as_json:
        typer.echo(json.dumps(res, indent=2))
        return
    _print_report(res, timed, torch_t, compiled_t, top_ops)
    for b, a in res.get("against", {}).get("backends", {}).items():
        m, o = timed[b], a["stages_ms"]
        console.print(f"{b}, taking turns with --against {against}: total median {m['total']['median']:.1f} against "
                      f"{o['total']['median']:.1f} ms, flow+pose {m['flowpose']['median']:.1f} against "
                      f"{o['flowpose']['median']:.1f} ms")


def _print_report(res: dict, timed: dict, torch_t: dict | None, compiled_t: dict | None, top_ops) -> None:
    from d3lvo_deploy.bench import BENCH_STAGES, BESIDE_ROW

    from d3lvo_deploy.cpu import CpuInfo

    cpu = CpuInfo(res["cpu"]["model"], res["cpu"]["cores"], tuple(res["cpu"]["isa"]))
    out.print(f"model: {res['timed']}", highlight=False)
    out.print(f"CPU: {cpu.line()}; numpy SGEMM peak {res['gemm_peak_gflops']:.0f} GFLOP/s", highlight=False)
    ovp = f", OpenVINO {res['ov_precision']}" if res.get("ov_precision") not in (None, "f32") else ""
    prep = res.get("prepare_threads", 1)
    t = Table(title=f"d3lvo bench: {res['size']}, {res['threads']} threads (project {prep}), {res['runs']} frames "
                    f"({res['precision']}{ovp}), ms per frame")
    t.add_column("stage", justify="right")
    t.add_column("GFLOP", justify="right")
    for b in timed:
        for q in ("median", "p90", "max"):
            t.add_column(f"{b} {q}" if q == "median" else q, justify="right")
    if torch_t:
        t.add_column("torch eager", justify="right")
    if compiled_t:
        t.add_column("torch.compile", justify="right")
    t.add_column(f"{res['best_backend']} GFLOP/s (% peak)", justify="right")
    gf = _row_gflops(res["stage_gflops"], any(BESIDE_ROW in tb for tb in timed.values()))
    for k in BENCH_STAGES:
        if not any(k in tb for tb in timed.values()):
            continue
        flops = gf.get(k)
        row = [k, "" if flops is None else f"{flops:.2f}"]
        for tb in timed.values():
            row += [f"{tb[k][q]:.1f}" if k in tb else "" for q in ("median", "p90", "max")]
        for tt in (torch_t, compiled_t):
            if tt:
                # torch times the network stages only: no projection, so its total is not comparable
                row.append(f"{tt[k]['median']:.1f}" if k in tt and k not in ("project", "total") else "")
        ms = timed[res["best_backend"]].get(k, {}).get("median")
        if flops and ms and k != "project":
            rate = flops / (ms / 1000.0)
            row.append(f"{rate:.0f} ({100 * rate / res['gemm_peak_gflops']:.0f} %)")
        else:
            row.append("")
        t.add_row(*row)
    out.print(t)
    for b, tb in timed.items():
        med, slowest = tb["total"]["median"], tb["total"]["max"]
        out.print(f"{b}: {1000.0 / med:.1f} frames/s end to end (incl. projection), median {med:.1f} ms "
                  f"{'within' if med <= 100.0 else 'over'} the 10 Hz budget of 100 ms, slowest frame {slowest:.1f} ms"
                  + (f"; pipelined (`d3lvo run --pipeline`: frame t+1 read ahead, encoded too on onnxruntime) "
                     f"{res['backends'][b]['pipelined_fps']:.1f} frames/s"
                     if res["backends"][b].get("pipelined_fps") else ""), highlight=False)
    msg = f"peak RSS {res['rss_mb']:.0f} MB" + (f" ({' and '.join(timed)} loaded together; one engine per "
                                                 "process needs less: --backend B)" if len(timed) > 1 else "")
    if torch_t:
        msg += (f"; network stages: {res['best_backend']} {res['best_over_torch']:.2f}x torch eager"
                + (f", onnxruntime {res['ort_over_torch']:.2f}x" if res['best_backend'] != "onnxruntime"
                   and "onnxruntime" in timed else ""))
    if compiled_t:
        msg += f", {res['best_over_torch_compile']:.2f}x torch.compile"
    out.print(msg + (" (above 1: faster)" if torch_t or compiled_t else ""), highlight=False)
    if top_ops:
        for stage, ops in top_ops.items():
            out.print(f"  {stage}: " + ", ".join(f"{op} {ms:.0f} ms" for op, ms in ops[:6]), highlight=False)
