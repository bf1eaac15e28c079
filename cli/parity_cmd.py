"""`d3lvo parity`: numerical agreement of the ONNX stages with the PyTorch checkpoint."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table
from rich.text import Text

from .common import friendly_errors, out


@friendly_errors
def parity_command(
    ckpt: Path = typer.Option(..., "--ckpt", help="The checkpoint the ONNX folder was exported from."),
    onnx: Path = typer.Option(..., "--onnx", help="Folder written by `d3lvo export`."),
    seq_dir: Path | None = typer.Option(None, "--seq-dir", help="KITTI-format frames (default: the real frames "
                                        "in ../shared/data, else a synthetic sequence)."),
    frames: int = typer.Option(3, "--frames", help="Frames to run (pairs = frames - 1)."),
    as_json: bool = typer.Option(False, "--json", help="Print the numbers and a pass flag as JSON."),
    backend: str = typer.Option("onnxruntime", "--backend", help="Engine to check: onnxruntime | openvino | auto (OpenVINO where "
                                 "installed; the output names the one checked)."),
    ov_precision: str = typer.Option("f32", "--ov-precision", help="With --backend openvino: f32 | bf16 (bf16 is "
                                     "reported, not expected to meet the fp32 tolerances)."),
) -> None:
    """Compare torch and the engine per stage output, along the chained pipeline, and against
    D3LVO.forward on each pair; exit 1 on failure.

    Example: d3lvo parity --ckpt runs/points.pt --onnx my_model --json
    """
    from d3lvo_deploy.backends import SessionConfig
    from d3lvo_deploy.extras import require

    require("torch", "onnx", what="d3lvo parity")
    from export.parity import POSE_R_TOL, POSE_T_TOL, STAGE_TOL, run_parity

    sc = SessionConfig(backend=backend, ov_precision=ov_precision)
    sc.check()
    sc = sc.resolved()  # the engine checked, by name: a pass on "auto" would not say which
    engine = sc.backend + (" (auto)" if backend == "auto" else "")
    rep = run_parity(ckpt, onnx, seq_dir, frames, sc)
    if as_json:
        typer.echo(json.dumps({**rep.to_dict(), "backend": sc.backend}, indent=2))
    else:
        t = Table(title=f"torch vs {engine} on {rep.frames} frames of {rep.data}")
        for c in ("stage", "output", "max abs", "max rel", f"ok (<= {STAGE_TOL:g} x max(1,|ref|))"):
            t.add_column(c)
        for stage, outs in rep.stages.items():
            for name, d in outs.items():
                t.add_row(stage, name, f"{d.max_abs:.2e}", f"{d.max_rel:.2e}", "yes" if d.ok else Text("NO", style="red"))
        out.print(t)
        out.print(f"chained relative pose: {rep.chained_t_m:.2e} m (<= {POSE_T_TOL:g}), "
                  f"{rep.chained_r_deg:.2e} deg (<= {POSE_R_TOL:g})", highlight=False)
        out.print(f"against D3LVO.forward on each pair: {rep.reference_t_m:.2e} m, {rep.reference_r_deg:.2e} deg "
                  f"(largest motion compared: {rep.motion_t_m:.3f} m, {rep.motion_r_deg:.3f} deg)", highlight=False)
        out.print(Text("PASS", style="bold green") if rep.passed else Text("FAIL", style="bold red"))
    if not rep.passed:
        raise typer.Exit(1)
