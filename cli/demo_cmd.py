"""`d3lvo demo`: the bundled model on two held-out synthetic drives, static and with traffic (each scored
beside its classical mode), and on real KITTI frames."""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import typer

from .common import console, friendly_errors, lead, out
from .progress import frame_progress

if TYPE_CHECKING:  # the [synth] extra; imported where the demo runs
    from d3lvo_deploy.backends import SessionConfig
    from d3lvo_deploy.direct import DirectConfig
    from d3lvo_deploy.evaluation import SequenceResult
    from d3lvo_deploy.onnx_model import StageModel
    from d3lvo_deploy.pipeline import RunSummary
    from d3lvo_deploy.sequence import KittiSequence
    from d3lvo_deploy.synth.generator import SynthConfig

DEMO_SEED = 909  # not among the training seeds (10-18) nor validation seeds (109-110)
DEMO_FRAMES = 220  # 140-150 m: long enough for the devkit's 100 m segments
DEMO_SIZE = (620, 188)  # the bundled model runs at 608x176; rendering at this size keeps the demo quick
# the second drive: vehicles that move around the camera, where the learned confidence is what the
# network adds to the classical tracker; a seed no training or validation drive uses, and the
# density and sensor effects of the held-out traffic drives (docs/evaluation.md)
DEMO_TRAFFIC_SEED = 910
DEMO_TRAFFIC = 5.0  # moving vehicles per 100 m of road
VIZ_EVERY = 20  # the traffic drive's pictures of what the network sees: every this-th frame


@dataclass(frozen=True)
class DemoDrive:
    """One held-out synthetic drive of the demo: its folder's name under --out and its label."""
    name: str
    label: str
    cfg: SynthConfig


@friendly_errors
def demo_command(
    out_dir: Path = typer.Option(Path(tempfile.gettempdir()) / "d3lvo-demo", "--out",
                                 help="Folder for the sequences, poses and plots (default: outside the checkout)."),
    frames: int = typer.Option(DEMO_FRAMES, "--frames", help="Length of each held-out synthetic drive."),
    traffic: bool = typer.Option(True, "--traffic/--no-traffic", help="Also the drive with moving vehicles "
                                 "(about a minute more the first time, to render it)."),
    onnx: Path | None = typer.Option(None, "--onnx", help="Model folder (default: the bundled model)."),
) -> None:
    """Render two held-out synthetic drives (static, and with traffic), run the ONNX pipeline and
    its classical mode on each, score both; then the real frames.

    Example: d3lvo demo --out /tmp/d3lvo-demo
    """
    from d3lvo_deploy.extras import require

    require("embreex", "matplotlib", what="d3lvo demo (it renders drives and plots them)")
    from d3lvo_deploy.direct import DirectConfig
    from d3lvo_deploy.evaluation import EvalReport
    from d3lvo_deploy.manifest import load_manifest
    from d3lvo_deploy.plot import plot_trajectories
    from d3lvo_deploy.sequence import KittiSequence
    from d3lvo_deploy.synth.generator import SynthConfig, check_config
    from d3lvo_deploy.bundled import bundled_model_dir, find_real_frames
    from d3lvo_deploy.backends import SessionConfig
    from d3lvo_deploy.onnx_model import StageModel
    from d3lvo_deploy.results import make_output_folder

    from .eval_cmd import _fmt, report_table
    from .run_cmd import latency_table, resolve_model_dir

    t_start = time.perf_counter()
    model_dir = resolve_model_dir(onnx)
    # a wrong --onnx is one error before any rendering; the classical mode's settings are the model's
    classical = DirectConfig.of_model(load_manifest(model_dir, verify_hashes=False)["model_config"])
    size = dict(width=DEMO_SIZE[0], height=DEMO_SIZE[1])
    drives = [DemoDrive("synthetic_heldout", "static", SynthConfig(frames=frames, seed=DEMO_SEED, **size))]
    if traffic:
        drives.append(DemoDrive("synthetic_traffic", "traffic", SynthConfig(
            frames=frames, seed=DEMO_TRAFFIC_SEED, traffic=DEMO_TRAFFIC, sensor_effects=True, **size)))
    for d in drives:
        check_config(d.cfg)
    # so is an --out that cannot be written (after the settings' checks, which leave nothing behind)
    make_output_folder(out_dir, "--out", "the demo's drives, poses and plots")
    for d in drives:
        _render(out_dir / d.name, d)

    sc = SessionConfig(backend="auto").resolved()  # OpenVINO where installed: the faster engine here
    engine = {"onnxruntime": "ONNX Runtime", "openvino": "OpenVINO"}[sc.backend]
    console.print(lead("2/3", "bold", f" D3LVO ({engine}, {'bundled model' if onnx is None else model_dir}) and, "
                                      "beside it, its classical mode (--method direct) on "
                                      + (" and ".join(d.label for d in drives)) + (" drive" if len(drives) == 1 else " drives")),
                  highlight=False)
    # opened once for every drive and the real frames: OpenVINO compiles (or loads) each stage once
    model = StageModel(model_dir, sc)
    reports, first_summary = {}, None
    every = max(1, min(VIZ_EVERY, frames // 4))  # a few pictures of a short drive too
    for d in drives:
        # with traffic, pictures of what the network sees: its confidence is low on what moves
        viz = out_dir / f"{d.name}_viz" if d.cfg.traffic else None
        res, base, summary = _score(out_dir, d, model, sc, classical, viz, every)
        if first_summary is None:
            first_summary = summary
        reports[f"D3LVO (ONNX), {d.label}"] = EvalReport([res], "none")
        reports[f"--method direct (no learning), {d.label}"] = EvalReport([base], "none")
        plot = plot_trajectories(out_dir / f"{d.name}.png", {"GT": res.gt_poses, "D3LVO (ONNX)": res.est_poses,
                                                             "--method direct": base.est_poses},
                                 title=f"held-out {d.label} drive: t_rel {_fmt(res.t_rel)} % (direct {_fmt(base.t_rel)} %)")
        console.print(f"{d.label}: poses {out_dir / (d.name + '_poses.txt')} (--method direct: {d.name}_direct.txt), "
                      f"plot {plot}" + (f", one frame in {every} as the network sees it (camera, depth, flow, "
                                        f"confidence) in {viz}" if viz else ""), highlight=False)
    out.print(report_table(reports))
    out.print(latency_table(first_summary))

    real = find_real_frames()
    if real is None:
        console.print(lead("3/3", "bold", " ../shared/data (real KITTI frames) not found: skipped"), highlight=False)
    else:
        console.print(lead("3/3", "bold", f" the 20 real KITTI frames in {real}"), highlight=False)
        bundled = Path(model_dir).resolve() == bundled_model_dir().resolve()
        _real_frames(out_dir, KittiSequence.open(real), model, sc, classical, bundled)
    mb = sum(f.stat().st_size for f in out_dir.rglob("*") if f.is_file()) / 1e6
    console.print(f"demo finished in {time.perf_counter() - t_start:.0f} s; {out_dir} holds {mb:.0f} MB "
                  "(delete it when done)", highlight=False)


def _real_frames(out_dir: Path, seq: KittiSequence, model: StageModel, sc: SessionConfig, classical: DirectConfig,
                 bundled: bool) -> None:
    """The model and its classical mode on real frames that have no ground truth, beside LiDAR-only
    odometry on the same scans (KISS-ICP, where the `[test]` extra installed it): how far each
    travels and where it ends, and how far that end is from the LiDAR-only one."""
    from d3lvo_deploy.direct import DirectOdometry
    from d3lvo_deploy.evaluation import path_length
    from d3lvo_deploy.lidar_reference import have_kiss_icp, kiss_icp_cam0
    from d3lvo_deploy.pipeline import RunConfig, run_sequence
    from d3lvo_deploy.plot import plot_trajectories
    from d3lvo_deploy.poses import read_poses
    from rich.table import Table

    path, direct_path = out_dir / "real_r0926_poses.txt", out_dir / "real_r0926_direct.txt"
    run_sequence(seq, None, RunConfig(out=path, overwrite=True), sc, model=model)
    run_sequence(seq, None, RunConfig(out=direct_path, overwrite=True),
                 odometry=DirectOdometry(seq.calib, classical))
    runs = {"D3LVO (ONNX)": read_poses(path).poses, "--method direct (no learning)": read_poses(direct_path).poses}
    ref = kiss_icp_cam0(seq) if have_kiss_icp() else None
    reference = {} if ref is None else {"LiDAR-only (KISS-ICP)": ref}
    table = Table(title="real frames (no ground truth), cam0")
    for col in ("estimate", "path m", "end point m") + (() if ref is None else ("end off LiDAR-only m",)):
        table.add_column(col, justify="left" if col == "estimate" else "right")
    for name, P in {**runs, **reference}.items():
        off = [] if ref is None else ["" if name in reference else f"{np.linalg.norm(P[-1, :3, 3] - ref[-1, :3, 3]):.2f}"]
        table.add_row(name, f"{path_length(P):.2f}", "(" + ", ".join(f"{v:.2f}" for v in P[-1, :3, 3]) + ")", *off)
    out.print(table)
    plot = plot_trajectories(out_dir / "real_r0926.png", {**reference, **runs}, title="real KITTI 2011_09_26 (no GT)")
    out.print("No ground truth exists for these frames: "
              + ("LiDAR-only odometry on the same scans is the reference (docs/evaluation.md)" if ref is not None else
                 "with the [test] extra (kiss-icp) the demo compares them with LiDAR-only odometry")
              + ("; the bundled model was trained on synthetic data only and is not meant for real KITTI accuracy."
                 if bundled else "."), highlight=False)
    console.print(f"poses: {path} (--method direct: {direct_path.name})\nplot:  {plot}", highlight=False)


def _render(seq_dir: Path, d: DemoDrive) -> None:
    """Render the drive into seq_dir, or reuse it where an earlier demo rendered exactly it."""
    from d3lvo_deploy.synth.generator import generate

    what = f"the held-out {d.label} synthetic drive"
    if _rendered(seq_dir, d.cfg):
        console.print(lead("1/3", "bold", f" reusing {what} rendered earlier in {seq_dir}"), highlight=False)
        return
    extra = f", {d.cfg.traffic:g} moving vehicles per 100 m, sensor effects" if d.cfg.traffic else ""
    console.print(lead("1/3", "bold", f" rendering {what} ({d.cfg.frames} frames, seed {d.cfg.seed}{extra}) "
                                      f"into {seq_dir}"), highlight=False)
    with frame_progress() as bar:
        task = bar.add_task("synth", total=d.cfg.frames, rate="")
        generate(seq_dir, d.cfg, progress=lambda n: bar.update(task, completed=n), resume=False)


def _score(out_dir: Path, d: DemoDrive, model: StageModel, sc: SessionConfig, classical: DirectConfig,
           viz: Path | None, every: int) -> tuple[SequenceResult, SequenceResult, RunSummary]:
    """The model and, beside it, its classical mode (the same solver with every point weighted 1)
    on the drive: both scored against its ground truth, and the model's run summary (latency);
    with `viz`, the run's pictures of every `every`-th frame (`d3lvo run --viz`) there."""
    from d3lvo_deploy.direct import DirectOdometry
    from d3lvo_deploy.evaluation import evaluate
    from d3lvo_deploy.pipeline import RunConfig
    from d3lvo_deploy.poses import read_poses
    from d3lvo_deploy.sequence import KittiSequence

    seq = KittiSequence.open(out_dir / d.name)
    if viz is not None:  # pictures of an earlier demo (another --frames) would mix with this run's
        for old in viz.glob("*.png"):
            old.unlink()
    poses_path, direct_path = out_dir / f"{d.name}_poses.txt", out_dir / f"{d.name}_direct.txt"
    summary = _run(f"run, {d.label}", seq, RunConfig(out=poses_path, overwrite=True, viz_dir=viz, viz_every=every),
                   sc, model=model)
    _run(f"direct, {d.label}", seq, RunConfig(out=direct_path, overwrite=True),
         odometry=DirectOdometry(seq.calib, classical))
    name = f"seed {d.cfg.seed}"
    return (evaluate(seq.ground_truth, read_poses(poses_path), name=name),
            evaluate(seq.ground_truth, read_poses(direct_path), name=name), summary)


def _run(label: str, seq: KittiSequence, rc, sc: SessionConfig | None = None, model: StageModel | None = None,
         odometry=None) -> RunSummary:
    """`run_sequence` under a progress bar labelled `label`: the network (`model`, opened with
    `sc`) or another tracker (`odometry`)."""
    from d3lvo_deploy.pipeline import run_sequence

    with frame_progress() as bar:
        task = bar.add_task(label, total=len(seq), rate="")
        engine = {} if sc is None else {"sc": sc}  # the direct tracker runs no engine
        return run_sequence(seq, None, rc, **engine, model=model, odometry=odometry,
                            progress=lambda n, tot, ms: bar.update(task, completed=n, rate=f"{ms:.0f} ms a frame"))


def _rendered(seq_dir: Path, cfg) -> bool:
    """Whether seq_dir already holds this exact drive, every frame written."""
    from d3lvo_deploy.synth.generator import rendered_settings

    # a synth.json missing or unreadable: not this drive, rendered again
    return (rendered_settings(seq_dir) == cfg.as_written() and (seq_dir / "poses.txt").is_file()
            and len(list((seq_dir / "image_2").glob("*.png"))) == cfg.frames)
