"""`d3lvo eval`: KITTI devkit metrics, ATE and RPE for one trajectory or a folder of them."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table

from d3lvo_deploy.evaluation import ALIGN_MODES, EvalReport, evaluate_files, pair_result_files
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.extras import require
from d3lvo_deploy.plot import plot_trajectories

from .common import console, friendly_errors, out


def _fmt(v: float | None, nd: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{nd}f}"


def report_table(report: EvalReport) -> Table:
    table = Table(title=f"KITTI odometry evaluation (align: {report.align})")
    for col in ("seq", "frames", "len m", "t_rel %", "r_rel °/100m", "ATE m", "RPE m", "RPE °", "segs"):
        table.add_column(col, justify="right")
    for s in report.sequences:
        table.add_row(s.name, str(s.frames), f"{s.path_length_m:.1f}", _fmt(s.t_rel), _fmt(s.r_rel), f"{s.ate:.3f}",
                      f"{s.rpe_t:.4f}", f"{s.rpe_r:.4f}", str(s.segments))
    if len(report.sequences) > 1:
        o = report.overall
        table.add_row("[bold]all[/]", str(o["frames"]), "", _fmt(o["t_rel"]), _fmt(o["r_rel"]), f"{o['ate']:.3f}",
                      f"{o['rpe_t']:.4f}", f"{o['rpe_r']:.4f}", str(o["segments"]))
    return table


@friendly_errors
def eval_command(
    gt: Path = typer.Option(..., "--gt", help="Ground-truth trajectory file, or a folder of NN.txt files."),
    est: Path = typer.Option(..., "--est", help="Estimated trajectory file, or a folder of NN.txt files."),
    align: str = typer.Option("none", "--align", help=f"Alignment before scoring: {'|'.join(ALIGN_MODES)}."),
    plot: Path | None = typer.Option(None, "--plot", help="Write a top-view (x-z) trajectory PNG here."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object instead of the table."),
) -> None:
    """Score trajectories with the KITTI devkit protocol (t_rel, r_rel) plus ATE and RPE."""
    if align not in ALIGN_MODES:
        raise D3LVOInputError(None, f"--align must be one of {', '.join(ALIGN_MODES)}, not {align!r}")
    if plot is not None:
        require("matplotlib", what="--plot")
    for p, what in ((gt, "ground truth"), (est, "estimate")):
        if not p.exists():
            raise D3LVOInputError(p, f"{what} not found")
    report = evaluate_files(pair_result_files(gt, est), align=align)
    for s in report.sequences:
        for note in s.notes:
            console.print(f"[yellow]note[/] {s.name}: {note}", highlight=False)
    if plot is not None:
        for s in report.sequences:
            target = plot if len(report.sequences) == 1 else plot.with_name(f"{plot.stem}_{s.name}{plot.suffix}")
            try:
                plot_trajectories(target, {"GT": s.gt_poses, f"estimate (align: {report.align})": s.est_poses},
                                  title=f"{s.name}: t_rel {_fmt(s.t_rel)} %, ATE {s.ate:.2f} m")
            except OSError as e:
                raise D3LVOInputError(target, f"cannot write the plot ({e.strerror})") from None
            console.print(f"plot written to {target}", highlight=False)
    if as_json:
        typer.echo(json.dumps(report.to_dict(), indent=2))
    else:
        out.print(report_table(report))
