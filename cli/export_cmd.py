"""`d3lvo export`: per-stage ONNX graphs plus manifest.json from a checkpoint, or a reduced-precision
copy of such a folder."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import typer

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.manifest import graph_files
from d3lvo_deploy.results import make_output_folder, remove_if_empty

from .common import console, friendly_errors, given_on_command_line


def default_calibration(tmp: Path) -> list[Path]:
    """Real frames when ../shared/data is present, plus a synthetic sequence: both looks the model meets."""
    from d3lvo_deploy.synth.generator import SynthConfig, generate
    from d3lvo_deploy.bundled import find_real_frames

    seqs = [generate(tmp / "calib_synth", SynthConfig(frames=8, seed=4242, width=620, height=188))]
    real = find_real_frames()
    return seqs + ([real] if real is not None else [])


def _number(val: str) -> bool | int | float | str:
    """"true" / "false", then an int, then a float (1E-6, -0.5), else the text itself."""
    if val.strip().lower() in ("true", "false"):
        return val.strip().lower() == "true"
    for cast in (int, float):
        try:
            return cast(val)
        except ValueError:
            pass
    return val


def solver_settings(pairs: list[str]) -> dict:
    """`--set KEY=VALUE` pairs -> {key: int | float | str}, solver settings only."""
    from models.config import check_solver_settings

    out: dict = {}
    for p in pairs:
        key, sep, val = p.partition("=")
        if not sep:
            raise D3LVOInputError(None, f"--set takes KEY=VALUE, not {p!r}")
        out[key] = tuple(_number(v) for v in val.split(",")) if "," in val else _number(val)
    check_solver_settings(out)
    return out


STAGING = ".export-"  # + the process id: the folder inside --out that an export fills first


def staging_folder(out: Path, overwrite: bool) -> Path:
    """A hidden folder inside `out` that the export fills, and `publish` then moves from: an export
    that fails or is stopped leaves an earlier one in `out` whole, and the moves stay on one file
    system whatever `out` is mounted on. `out` must be new, empty, or with --overwrite hold an
    earlier export (its manifest.json): never only other files. A staging folder that a killed
    export left is removed."""
    if out.is_dir():
        for left in out.glob(STAGING + "*"):
            shutil.rmtree(left, ignore_errors=True)
    if out.is_dir() and any(out.iterdir()):
        if not (out / "manifest.json").is_file():
            raise D3LVOInputError(out, "holds files but no manifest.json (not an export): give a new or empty "
                                       "folder for the exported graphs")
        if not overwrite:
            raise D3LVOInputError(out, "already holds an export; --overwrite replaces it once the new one is "
                                       "complete, or give another folder")
    return make_output_folder(out, "--out", "the exported graphs") / f"{STAGING}{os.getpid()}"


def publish(stage: Path, out: Path) -> None:
    """The complete export in `stage` moved into `out` file by file, manifest.json last, then the
    earlier export's graphs that the new one lacks removed; other files in `out` (a model card,
    the checkpoint it was exported from) stay. A stop in these few renames can leave new graphs
    beside the earlier manifest, which their sha256 then refuses to load."""
    earlier: set[str] = set()
    if (out / "manifest.json").is_file():
        try:
            earlier = {f for f in graph_files(json.loads((out / "manifest.json").read_text())) if Path(f).name == f}
        except (ValueError, KeyError, TypeError, AttributeError):
            pass  # an unreadable manifest: its graphs are replaced where the new export has them
    written = [f.name for f in stage.iterdir() if f.name != "manifest.json"]
    for name in written:
        os.replace(stage / name, out / name)
    os.replace(stage / "manifest.json", out / "manifest.json")
    for name in earlier - set(written):
        (out / name).unlink(missing_ok=True)


def _check_conversion(onnx_dir: Path, out: Path, precision: str, export_options: list[str]) -> None:
    """--onnx converts a folder as it was exported: an fp32 one, into another folder, with no export
    option (the folder fixed its size, opset, batch axis and solver)."""
    from d3lvo_deploy.manifest import load_manifest

    if precision == "fp32":
        raise D3LVOInputError(None, "--onnx converts an exported folder: it needs --precision fp16 or int8")
    if export_options:
        raise D3LVOInputError(onnx_dir, f"--onnx converts the folder as it was exported; {export_options[0]} needs --ckpt")
    m = load_manifest(onnx_dir, verify_hashes=False)  # `quantize_folder` checks the hashes, before it writes
    if m.get("precision", "fp32") != "fp32":
        raise D3LVOInputError(onnx_dir, f"holds an {m['precision']} model; --onnx converts an fp32 export")
    if out.resolve() == onnx_dir.resolve():
        raise D3LVOInputError(out, "is the --onnx folder itself; write the converted model to another folder")


@friendly_errors
def export_command(
    ctx: typer.Context,
    ckpt: Path | None = typer.Option(None, "--ckpt", help="D3LVO checkpoint (from `d3lvo train`)."),
    onnx_dir: Path | None = typer.Option(None, "--onnx", help="Instead of --ckpt: an fp32 model folder from "
                                         "`d3lvo export` to convert with --precision fp16|int8."),
    out: Path = typer.Option(..., "--out", help="Output folder for the .onnx files and manifest.json."),
    opset: int = typer.Option(17, "--opset", help="ONNX opset, 16 (GridSample) to 20 (torch's exporter)."),
    height: int | None = typer.Option(None, "--height", help="Input height (default: the checkpoint's)."),
    width: int | None = typer.Option(None, "--width", help="Input width (default: the checkpoint's)."),
    dynamic_batch: bool = typer.Option(False, "--dynamic-batch", help="Leave the batch dimension dynamic."),
    precision: str = typer.Option("fp32", "--precision", help="fp32 | fp16 | int8 (static, QDQ, per-channel)."),
    solver: list[str] = typer.Option([], "--set", help="Solver setting KEY=VALUE without weights (point solver: "
                                     "pt_iters, pt_capacity, pt_min_gradient, pt_stop, pt_damping, pt_scale_every, pt_median_stride, pt_refine, pt_affine, pt_fine_restart, pt_restart_depth, pt_scan_gate, pt_conf_power, pt_gate, pt_conf_full, pt_select, pt_select_rotation, pt_select_unexplained, pt_select_scan, pt_select_scan_pass, pt_select_share, pt_classical_chain, pt_select_hold; cell solver: "
                                     "gn_points, gn_iters, gn_huber, gn_damping, gn_lidar_pool), e.g. --set "
                                     "pt_iters=10,10,10; repeatable."),
    calib_seq: list[Path] = typer.Option([], "--calib-seq", help="INT8 calibration sequence (repeatable; default: "
                                         "the real frames in ../shared/data and a synthetic sequence)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an earlier export in --out (once the new "
                                   "one is complete and checked)."),
) -> None:
    """Export completion, encoder and flow+pose as standard-op ONNX graphs, checked and hashed.

    Example: d3lvo export --ckpt runs/points.pt --out my_model   (then d3lvo run DRIVE --onnx my_model);
    d3lvo export --onnx my_model --precision int8 --out my_model_int8   (no second export)
    """
    import tempfile

    from d3lvo_deploy.extras import require

    require("torch", "onnx", what="d3lvo export")
    from export.onnx_export import ExportConfig, export_checkpoint

    if precision not in ("fp32", "fp16", "int8"):
        raise D3LVOInputError(None, f"--precision must be fp32, fp16 or int8, not {precision!r}")
    if (ckpt is None) == (onnx_dir is None):
        raise D3LVOInputError(None, "give either --ckpt (a checkpoint to export) or --onnx (an fp32 model folder "
                                    "to convert with --precision fp16|int8)")
    if calib_seq and precision != "int8":
        raise D3LVOInputError(calib_seq[0], "--calib-seq calibrates an INT8 export: it needs --precision int8")
    if out.exists() and not out.is_dir():  # before an fp32 export and a calibration that would come first
        raise D3LVOInputError(out, "is a file; --out names the folder for the exported graphs")
    for s in calib_seq:  # before the fp32 export that precedes the calibration
        from d3lvo_deploy.sequence import KittiSequence

        KittiSequence.open(s)
    if onnx_dir is not None:
        given = [f"--{name.replace('_', '-')}" for name in ("opset", "height", "width", "dynamic_batch")
                 if given_on_command_line(ctx, name)] + (["--set"] if given_on_command_line(ctx, "solver") else [])
        _check_conversion(onnx_dir, out, precision, given)
    made = not out.exists()
    stage = staging_folder(out, overwrite)
    try:
        with tempfile.TemporaryDirectory(prefix="d3lvo-export-") as tmpd:
            fp32_dir = onnx_dir or (stage if precision == "fp32" else Path(tmpd) / "fp32")
            if ckpt is not None:
                with console.status("exporting"):
                    m = export_checkpoint(ckpt, ExportConfig(out=fp32_dir, opset=opset, height=height, width=width,
                                                             dynamic_batch=dynamic_batch,
                                                             solver=solver_settings(solver)),
                                          progress=lambda name: console.print(f"  {name}.onnx checked", highlight=False))
            if precision != "fp32":
                from export.quantize import quantize_folder

                seqs: list[Path] = []
                if precision == "int8":
                    seqs = list(calib_seq) or default_calibration(Path(tmpd))
                with console.status(f"converting to {precision}"):
                    m = quantize_folder(fp32_dir, stage, precision, seqs)
        publish(stage, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)  # an export that failed or was stopped
        if made:
            remove_if_empty(out)
    files = graph_files(m)
    size = sum((out / f).stat().st_size for f in files) / 1e6
    console.print(f"wrote {', '.join(files)} + manifest.json to {out} "
                  f"({size:.1f} MB, {m['precision']}, opset {m['opset']}, {m['input']['width']}x{m['input']['height']})",
                  highlight=False)
