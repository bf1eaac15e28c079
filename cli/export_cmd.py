"""`d3lvo export`: per-stage ONNX graphs plus manifest.json from a checkpoint."""

from __future__ import annotations

from pathlib import Path

import typer

from .common import console, friendly_errors


@friendly_errors
def export_command(
    ckpt: Path = typer.Option(..., "--ckpt", help="D3LVO checkpoint (from `d3lvo train`)."),
    out: Path = typer.Option(..., "--out", help="Output folder for the .onnx files and manifest.json."),
    opset: int = typer.Option(17, "--opset", help="ONNX opset (16+: GridSample)."),
    height: int | None = typer.Option(None, "--height", help="Input height (default: the checkpoint's)."),
    width: int | None = typer.Option(None, "--width", help="Input width (default: the checkpoint's)."),
    dynamic_batch: bool = typer.Option(False, "--dynamic-batch", help="Leave the batch dimension dynamic."),
) -> None:
    """Export completion, encoder and flow+pose as standard-op ONNX graphs, checked and hashed."""
    from export.onnx_export import ExportConfig, export_checkpoint

    with console.status("exporting"):
        m = export_checkpoint(ckpt, ExportConfig(out=out, opset=opset, height=height, width=width,
                                                 dynamic_batch=dynamic_batch),
                              progress=lambda name: console.print(f"  {name}.onnx checked", highlight=False))
    size = sum((out / s["file"]).stat().st_size for s in m["stages"].values()) / 1e6
    console.print(f"wrote {', '.join(s['file'] for s in m['stages'].values())} + manifest.json to {out} "
                  f"({size:.1f} MB, opset {m['opset']}, {m['input']['width']}x{m['input']['height']})", highlight=False)
