"""`d3lvo bench`: per-stage latency, frames/s and peak memory of the ONNX pipeline vs torch eager."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import typer
from rich.table import Table

from d3lvo_deploy.errors import D3LVOInputError

from .common import console, friendly_errors, out


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


@friendly_errors
def bench_command(
    onnx: Path | None = typer.Option(None, "--onnx", help="Exported model folder (default: the bundled model)."),
    ckpt: Path | None = typer.Option(None, "--ckpt", help="Or a checkpoint: exported to a temporary folder first."),
    height: int | None = typer.Option(None, "--height", help="Export --ckpt at this height; without --ckpt, time the default network (D3LVOConfig()) at this size."),
    width: int | None = typer.Option(None, "--width", help="... and this width (e.g. --height 352 --width 1216)."),
    threads: int = typer.Option(2, "--threads", help="Threads for onnxruntime and torch."),
    runs: int = typer.Option(20, "--runs", help="Timed frames after warm-up."),
    seq_dir: Path | None = typer.Option(None, "--seq-dir", help="Frames to run on (default: real frames, else synthetic)."),
    torch_compare: bool = typer.Option(True, "--torch/--no-torch", help="Also time torch eager on the same stages."),
    as_json: bool = typer.Option(False, "--json", help="Print the numbers as JSON."),
    profile: Path | None = typer.Option(None, "--profile", help="Write onnxruntime profiles here and list the top ops."),
    precision: str = typer.Option("fp32", "--precision", help="With --ckpt or --height/--width: export at fp32 | fp16 | "
                                  "int8 first (INT8 calibrated as `d3lvo export` does). Torch stays FP32."),
) -> None:
    """Median/p90/min latency per stage, frames/s, peak RSS, and the ORT speed-up over torch eager."""
    from d3lvo_deploy.bench import BENCH_STAGES, bench_onnx, peak_rss_mb
    from d3lvo_deploy.bundled import find_real_frames
    from d3lvo_deploy.manifest import load_manifest
    from d3lvo_deploy.onnx_model import SessionConfig
    from d3lvo_deploy.sequence import KittiSequence

    if runs < 1:
        raise D3LVOInputError(None, "--runs must be at least 1")
    if (height is None) != (width is None):
        raise D3LVOInputError(None, "give --height and --width together")
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
    if ckpt is not None or default_network:
        from d3lvo_deploy.extras import require

        require("torch", "onnx", what="d3lvo bench with --ckpt or --height/--width (it exports first)")
    if seq_dir is None and find_real_frames() is None:
        from d3lvo_deploy.extras import require

        require("embreex", what="d3lvo bench without --seq-dir or ../shared/data (it renders frames)")
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
        manifest = load_manifest(onnx)
        seq = KittiSequence.open(seq_dir or _bench_frames(tmp))
        sc = SessionConfig(threads=threads, profile_dir=str(profile) if profile else None)
        with console.status(f"timing onnxruntime ({runs} frames)"):
            ort_t = bench_onnx(onnx, seq, sc, runs).summary()
        top_ops = None
        if profile is not None:
            from d3lvo_deploy.bench import profile_summary

            top_ops = profile_summary(sorted(str(p) for p in profile.glob("*.json")))
        rss = peak_rss_mb()  # before torch is imported: what a vehicle process needs
        torch_t = None
        if torch_compare:
            try:
                from models.bench_torch import bench_torch
                from models.config import D3LVOConfig
            except ImportError:
                console.print("torch is not installed: no torch comparison", highlight=False)
            else:
                with console.status(f"timing torch eager ({runs} frames)"):
                    torch_t = bench_torch(D3LVOConfig.from_dict(manifest["model_config"]), seq, threads, runs).summary()
    res = {
        "model": str(onnx), "size": f"{manifest['input']['width']}x{manifest['input']['height']}",
        "precision": manifest.get("precision", "fp32"), "flow_levels": manifest["model_config"]["flow_levels"],
        "threads": threads, "runs": runs, "frames_from": str(seq.root),
        "stages_ms": ort_t, "total_ms_median": ort_t["total"]["median"],
        "fps": 1000.0 / ort_t["total"]["median"], "rss_mb": rss,
    }
    if torch_t is not None:
        net = ("completion", "encoder", "flowpose")
        t_ort = sum(ort_t[k]["median"] for k in net if k in ort_t)
        t_torch = sum(torch_t[k]["median"] for k in net if k in torch_t)
        res["torch_stages_ms"] = torch_t
        res["ort_over_torch"] = t_torch / t_ort  # speed-up of ORT over torch eager on the network stages
    if top_ops is not None:
        res["top_ops_ms"] = top_ops
    if as_json:
        typer.echo(json.dumps(res, indent=2))
        return
    t = Table(title=f"d3lvo bench: {res['size']}, {threads} threads, {runs} frames ({res['precision']})")
    for c in ("stage", "ORT median", "p90", "min", "max") + (("torch median", "speed-up") if torch_t else ()):
        t.add_column(c, justify="right")
    for k in BENCH_STAGES:
        if k not in ort_t:
            continue
        row = [k] + [f"{ort_t[k][q]:.1f}" for q in ("median", "p90", "min", "max")]
        if torch_t:
            # torch times the network stages only: no projection, so its total is not comparable
            tm = torch_t.get(k, {}).get("median") if k not in ("project", "total") else None
            row += ["" if tm is None else f"{tm:.1f}", "" if tm is None else f"{tm / max(ort_t[k]['median'], 1e-9):.2f}x"]
        t.add_row(*row)
    out.print(t)
    budget = "within" if res["total_ms_median"] <= 100.0 else "over"
    slowest = ort_t["total"]["max"]
    msg = (f"{res['fps']:.1f} frames/s end to end (incl. projection), {budget} the 10 Hz budget of 100 ms "
           f"(slowest frame {slowest:.1f} ms{'' if slowest <= 100.0 else ', over budget'}); "
           f"peak RSS {rss:.0f} MB")
    if torch_t:
        msg += f"; network stages: ORT/torch speed-up {res['ort_over_torch']:.2f}x (above 1: ORT faster)"
    out.print(msg, highlight=False)
    if top_ops:
        for stage, ops in top_ops.items():
            out.print(f"  {stage}: " + ", ".join(f"{op} {ms:.0f} ms" for op, ms in ops[:6]), highlight=False)
