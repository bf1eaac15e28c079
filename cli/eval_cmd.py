"""`d3lvo eval`: KITTI devkit metrics, ATE and RPE for one trajectory or a folder of them."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.text import Text
from rich.table import Table

from d3lvo_deploy.evaluation import ALIGN_MODES, EvalReport, evaluate_files, pair_result_files
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.extras import require
from d3lvo_deploy.plot import plot_path, plot_trajectories

from .common import console, friendly_errors, lead, out


def _fmt(v: float | None, nd: int = 2) -> str:
    return "n/a" if v is None or v != v else f"{v:.{nd}f}"  # None or NaN


def report_table(report: EvalReport | dict[str, EvalReport]) -> Table:
    """One table; with several estimates (a dict by label) one row per estimate and sequence."""
    reports = report if isinstance(report, dict) else {"": report}
    align = next(iter(reports.values())).align
    table = Table(title=f"KITTI odometry evaluation (align: {align})")
    if len(reports) > 1:
        table.add_column("estimate", justify="left")
    for col in ("seq", "frames", "len m", "t_rel %", "r_rel °/100m", "ATE m", "RPE m", "RPE °", "segs"):
        table.add_column(col, justify="right")
    for label, rep in reports.items():
        lead = [label] if len(reports) > 1 else []
        for s in rep.sequences:
            table.add_row(*lead, s.name, str(s.frames), f"{s.path_length_m:.1f}", _fmt(s.t_rel), _fmt(s.r_rel),
                          f"{s.ate:.3f}", _fmt(s.rpe_t, 4), _fmt(s.rpe_r, 4), str(s.segments))
        if len(rep.sequences) > 1:
            o = rep.overall
            table.add_row(*lead, Text("all", style="bold"), str(o["frames"]), "", _fmt(o["t_rel"]), _fmt(o["r_rel"]),
                          f"{o['ate']:.3f}", _fmt(o["rpe_t"], 4), _fmt(o["rpe_r"], 4), str(o["segments"]))
    return table


def _labels(paths: list[Path]) -> list[str]:
    """Short names for the estimates: file or folder names, with the parent folder where they clash."""
    names = [p.stem if p.is_file() else p.name for p in paths]
    if len(set(names)) < len(names):
        names = [f"{p.parent.name}/{n}" for p, n in zip(paths, names)]
    if len(set(names)) < len(names):
        names = [str(p) for p in paths]
    return names


@friendly_errors
def eval_command(
    gt: Path = typer.Option(..., "--gt", help="Ground-truth trajectory file, or a folder of NN.txt files."),
    est: list[Path] = typer.Option(..., "--est", help="Estimated trajectory file, or a folder of NN.txt files; "
                                   "give --est several times to compare methods in one table."),
    align: str = typer.Option("none", "--align", help=f"Alignment before scoring: {'|'.join(ALIGN_MODES)}."),
    plot: Path | None = typer.Option(None, "--plot", help="Write a top-view (x-z) trajectory plot here: .png "
                                     "(the default suffix) or any kind matplotlib writes (.pdf, .svg, .jpg, ...); "
                                     "for folders one per sequence, STEM_SEQUENCE.png (cmp_09.png for --plot "
                                     "cmp.png)."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object instead of the table."),
) -> None:
    """Score trajectories with the KITTI devkit protocol (t_rel, r_rel) plus ATE and RPE.

    Example: d3lvo eval --gt poses.txt --est d3lvo.txt --est direct.txt --plot cmp.png
    """
    if align not in ALIGN_MODES:
        raise D3LVOInputError(None, f"--align must be one of {', '.join(ALIGN_MODES)}, not {align!r}")
    if plot is not None:
        require("matplotlib", what="--plot")
        plot = plot_path(plot)
    for p, what in [(gt, "ground truth")] + [(e, "estimate") for e in est]:
        if not p.exists():
            raise D3LVOInputError(p, f"{what} not found")
    reports = {}
    for label, e in zip(_labels(est), est):
        pairs, unpaired = pair_result_files(gt, e)
        if unpaired:
            console.print(lead("note", "yellow", f" {e}: {', '.join(unpaired)} not scored: no file of that name "
                                                 f"in {gt}"), highlight=False)
        if gt.is_dir():  # scored on fewer sequences than the ground truth holds: said, as methods compare
            missing = sorted(f.name for f in gt.glob("*.txt") if not (e / f.name).is_file())
            if missing:
                more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
                console.print(lead("note", "yellow", f" {e}: no estimate for {', '.join(missing[:5])}{more} of {gt}: "
                                                     "those sequences are not scored"), highlight=False)
        reports[label] = evaluate_files(pairs, align=align, per_sequence=gt.is_dir())
    many = len(reports) > 1
    for label, report in reports.items():
        for s in report.sequences:
            for note in s.notes:
                who = f"{label} {s.name}" if many and label != s.name else s.name
                console.print(lead("note", "yellow", f" {who}: {note}"), highlight=False)
    if plot is not None:
        first = next(iter(reports.values()))
        for s in first.sequences:
            one = len(first.sequences) == 1 and not first.per_sequence  # folders: named by sequence
            target = plot if one else plot.with_name(f"{plot.stem}_{s.name}{plot.suffix}")
            curves = {"GT": s.gt_poses}
            for label, report in reports.items():  # the same sequence of each estimate, by name
                r = next((x for x in report.sequences if x.name == s.name), None)
                if r is not None:
                    curves[f"{label if many else 'estimate'} (align: {align}, t_rel {_fmt(r.t_rel)} %)"] = r.est_poses
            title = s.name if many else f"{s.name}: t_rel {_fmt(s.t_rel)} %, ATE {s.ate:.2f} m"
            try:
                plot_trajectories(target, curves, title=title)
            except OSError as e:
                raise D3LVOInputError(target, f"cannot write the plot ({e.strerror})") from None
            console.print(f"plot written to {target}", highlight=False)
    if as_json:
        data = next(iter(reports.values())).to_dict() if not many else \
            {"estimates": {label: r.to_dict() for label, r in reports.items()}}
        typer.echo(json.dumps(data, indent=2))
    else:
        out.print(report_table(reports if many else next(iter(reports.values()))))
