"""`d3lvo run`: the ONNX pipeline over a KITTI-format sequence, poses written as they come."""

from __future__ import annotations

import warnings
from pathlib import Path

import typer
from rich.markup import escape
from rich.table import Table

from d3lvo_deploy.errors import D3LVOInputError

from .common import console, friendly_errors, out
from .progress import frame_progress


def resolve_model_dir(onnx: Path | None) -> Path:
    if onnx is not None:
        return onnx
    from d3lvo_deploy.bundled import bundled_model_dir

    return bundled_model_dir()


def latency_table(stats: dict) -> Table:
    t = Table(title="latency per frame (ms)")
    for c in ("stage", "mean", "p90", "max"):
        t.add_column(c, justify="right")
    for k in ("read", "project", "completion", "encoder", "flowpose", "total"):
        if k in stats:
            s = stats[k]
            t.add_row(k, f"{s['mean']:.1f}", f"{s['p90']:.1f}", f"{s['max']:.1f}")
    return t


@friendly_errors
def run_command(
    seq_dir: Path | None = typer.Option(None, "--seq-dir", help="KITTI odometry sequence folder."),
    kitti_root: Path | None = typer.Option(None, "--kitti-root", help="KITTI odometry root (sequences/, poses/)."),
    sequence: str | None = typer.Option(None, "--sequence", help="Sequence id under --kitti-root, e.g. 09."),
    out_path: Path | None = typer.Option(None, "--out", help="Trajectory file to write (cam0 poses, first = identity)."),
    sequences: str | None = typer.Option(None, "--sequences", help="Many sequences under --kitti-root: 00-10 or 00,05."),
    out_dir: Path | None = typer.Option(None, "--out-dir", help="With --sequences: folder for NN.txt trajectories."),
    engine: str = typer.Option("local", "--engine", help="With --sequences: sequential | local (processes) | ray."),
    workers: int = typer.Option(2, "--workers", help="With --sequences: parallel workers."),
    address: str | None = typer.Option(None, "--address", help="With --engine ray: cluster address (default: local)."),
    chunk: int = typer.Option(1000, "--chunk", help="With --sequences: frames per task (long sequences are split)."),
    overlap: int = typer.Option(2, "--overlap", help="With --sequences: frames shared by consecutive chunks (the "
                                "stitch anchors at the last one, so each chunk's cold-started first pair is dropped)."),
    onnx: Path | None = typer.Option(None, "--onnx", help="Exported model folder (default: the bundled model)."),
    fmt: str = typer.Option("kitti", "--format", help="kitti | tum."),
    start: int = typer.Option(0, "--start", help="First frame."),
    end: int | None = typer.Option(None, "--end", help="One past the last frame."),
    resume: bool = typer.Option(False, "--resume", help="Continue an interrupted run from its last written pose."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an --out file that already holds poses."),
    viz: Path | None = typer.Option(None, "--viz", help="Folder for pictures of what the network sees (image, LiDAR "
                                    "and completed depth, flow, pose confidence), one PNG per --viz-every frames."),
    viz_every: int = typer.Option(10, "--viz-every", help="With --viz or --rerun: pictures of every N-th frame."),
    rerun: Path | None = typer.Option(None, "--rerun", help="Write a Rerun recording (FILE.rrd: trajectory, LiDAR "
                                      "points, camera images and network outputs) for the Rerun viewer (the \\[rerun] extra)."),
    gt: Path | None = typer.Option(None, "--gt", help="Ground truth to score against (default: found beside the sequence)."),
    plot: Path | None = typer.Option(None, "--plot", help="Write a trajectory PNG (needs ground truth or not)."),
    provider: str = typer.Option("cpu", "--provider", help="cpu | cuda | tensorrt (falls back to cpu)."),
    threads: int = typer.Option(0, "--threads", help="Inference threads (0: all cores)."),
    backend: str = typer.Option("auto", "--backend", help="onnxruntime | openvino (the \\[openvino] extra) | auto "
                                "(openvino where installed, else onnxruntime; `d3lvo bench` times both)."),
    ov_precision: str = typer.Option("f32", "--ov-precision", help="With --backend openvino: f32 | bf16 (bf16 uses "
                                     "the CPU's AVX512_BF16/AMX paths; see the README's precision table)."),
    optimization: str = typer.Option("all", "--optimization", help="Graph optimisation: disable|basic|extended|all."),
    realtime: bool = typer.Option(False, "--realtime", help="Pace frames by times.txt, like a live 10 Hz sensor."),
    method: str = typer.Option("d3lvo", "--method", help="d3lvo (the ONNX network) | direct (the no-learning "
                               "photometric LiDAR-visual tracker the network is measured against: the model's "
                               "own solver and point settings, every point weighted 1)."),
) -> None:
    """Estimate the trajectory of a sequence with the ONNX stages (no torch needed)."""
    from d3lvo_deploy.onnx_model import SessionConfig
    from d3lvo_deploy.pipeline import RunConfig, execute_run, prepare_run
    from d3lvo_deploy.sequence import KittiSequence

    if method not in ("d3lvo", "direct"):
        raise D3LVOInputError(None, f"--method must be d3lvo or direct, not {method!r}")
    if plot is not None:
        from d3lvo_deploy.extras import require

        require("matplotlib", what="--plot")
    if sequences is not None:
        if method != "d3lvo":
            raise D3LVOInputError(None, "--sequences runs the network only; run --method direct per sequence")
        return _run_many(kitti_root, sequences, out_dir, onnx, engine, workers, address, chunk, overlap, backend)
    if out_path is None:
        raise D3LVOInputError(None, "--out FILE is required (or --sequences with --out-dir)")
    if (seq_dir is None) == (kitti_root is None):
        raise D3LVOInputError(None, "give either --seq-dir DIR or --kitti-root R --sequence NN")
    if kitti_root is not None:
        if sequence is None:
            raise D3LVOInputError(kitti_root, "--kitti-root needs --sequence (e.g. 09)")
        seq = KittiSequence.from_kitti_root(kitti_root, sequence)
    else:
        seq = KittiSequence.open(seq_dir, gt=gt)
    if gt is not None and kitti_root is not None:
        seq = KittiSequence.open(seq.root, gt=gt)
    sc = SessionConfig(provider=provider, threads=threads, optimization=optimization, backend=backend,
                       ov_precision=ov_precision)
    sc.check()
    odometry = None
    if method == "direct":
        from d3lvo_deploy.direct import DirectConfig, DirectOdometry
        from d3lvo_deploy.manifest import load_manifest

        # the classical mode of the model the run would use (the bundled one by default): its
        # point selection and solver settings, with no learned confidence
        config = load_manifest(resolve_model_dir(onnx))["model_config"]
        odometry, model_dir = DirectOdometry(seq.calib, DirectConfig.of_model(config)), None
    else:
        model_dir = resolve_model_dir(onnx)
    if viz is not None and (method != "d3lvo" or viz_every < 1):
        raise D3LVOInputError(viz, "--viz shows the network's inputs and outputs: needs --method d3lvo and --viz-every >= 1")
    if rerun is not None and viz_every < 1:
        raise D3LVOInputError(rerun, "--viz-every must be at least 1")
    rc = RunConfig(out=out_path, fmt=fmt, start=start, end=end, resume=resume, overwrite=overwrite, realtime=realtime,
                   viz_dir=viz, viz_every=viz_every, rerun_path=rerun)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # every argument, the output file and the model are checked before the progress bar
        with console.status("loading the model"):
            plan = prepare_run(seq, model_dir, rc, sc, odometry=odometry)
    _print_warnings(caught)
    label = "D3LVO (ONNX)" if method == "d3lvo" else "direct tracker"
    if plan.finished:
        console.print(f"{out_path} already holds all {plan.n} poses of frames {plan.rc.start}..{plan.rc.end - 1}: "
                      "nothing to run (--overwrite starts over)", highlight=False)
        _score(seq, out_path, plan.rc.fmt, start, end, plot, label)
        return
    if method == "d3lvo":
        console.print(f"model {model_dir} on {plan.odo.model.backend}", highlight=False)
    if plan.done.shape[0]:
        console.print(f"resuming after {len(plan.done)} poses already in {out_path}", highlight=False)
    with warnings.catch_warnings(record=True) as caught, frame_progress() as bar:
        warnings.simplefilter("always")
        task = bar.add_task("run", total=plan.n, rate="")

        def tick(done: int, total: int, ms: float) -> None:
            bar.update(task, completed=done, total=total, rate=f"{1000.0 / max(ms, 1e-6):.1f} frames/s")

        try:
            summary = execute_run(plan, progress=tick)
        except KeyboardInterrupt:
            bar.stop()
            console.print(f"[yellow]interrupted[/]: the poses so far are in {out_path}; the same command with "
                          "--resume continues from there", highlight=False)
            raise typer.Exit(130) from None
    _print_warnings(caught)
    out.print(latency_table(summary.stats()))
    out.print(f"{summary.frames} poses in {out_path} ({plan.rc.fmt}, cam0, first pose identity)", highlight=False)
    _score(seq, out_path, plan.rc.fmt, start, end, plot, label)


def _print_warnings(caught) -> None:
    seen = set()
    for w in caught:
        msg = str(w.message)
        if msg not in seen:
            seen.add(msg)
            console.print(f"[yellow]warning[/] {escape(msg)}", highlight=False)


def _run_many(kitti_root, spec, out_dir, onnx, engine, workers, address, chunk, overlap, backend) -> None:
    import os
    import time

    from d3lvo_deploy.backends import SessionConfig

    from d3lvo_deploy.evaluation import evaluate_files
    from d3lvo_deploy.scaleout import parse_sequences, run_many

    from .eval_cmd import report_table

    if kitti_root is None or out_dir is None:
        raise D3LVOInputError(None, "--sequences needs --kitti-root R and --out-dir OUT")
    names = parse_sequences(spec)
    dirs = {n: kitti_root / "sequences" / n for n in names}
    for n, d in dirs.items():
        if not d.is_dir():
            raise D3LVOInputError(d, f"sequence {n} not found under {kitti_root}")
    from d3lvo_deploy.sequence import KittiSequence
    from d3lvo_deploy.scaleout import plan_chunks

    total = sum(len(plan_chunks(len(KittiSequence.open(d)), chunk, overlap)) for d in dirs.values())
    # the machine's cores split between the workers, on the engine --backend names (resolved here,
    # so every worker runs the same one)
    sc = SessionConfig(threads=max(1, (os.cpu_count() or 1) // max(workers, 1)), backend=backend)
    sc.check()
    sc = sc.resolved()
    t0 = time.perf_counter()
    with frame_progress() as bar:
        task = bar.add_task(f"{engine} x{workers}", total=total, rate="chunks")
        residuals = run_many(dirs, resolve_model_dir(onnx), out_dir, engine=engine, workers=workers, chunk=chunk,
                             overlap=overlap, address=address, sc=sc, on_chunk=lambda c: bar.advance(task),
                             on_sequence=lambda n, p, r: console.print(f"{n}: {p} (overlap residual {r:.1e} m)",
                                                                         highlight=False))
    console.print(f"{len(residuals)} sequences in {time.perf_counter() - t0:.1f} s", highlight=False)
    pairs = [(kitti_root / "poses" / f"{n}.txt", out_dir / f"{n}.txt") for n in names
             if (kitti_root / "poses" / f"{n}.txt").is_file()]
    if pairs:
        out.print(report_table(evaluate_files(pairs)))


def _score(seq, out_path: Path, fmt: str, start: int, end: int | None, plot: Path | None, label: str) -> None:
    from d3lvo_deploy.evaluation import EvalReport, evaluate
    from d3lvo_deploy.geometry import relative
    from d3lvo_deploy.plot import plot_trajectories
    from d3lvo_deploy.poses import Trajectory, read_poses

    from .eval_cmd import report_table

    est = read_poses(out_path, fmt)
    gt = seq.ground_truth
    if gt is None:
        console.print("no ground truth for this sequence: no metrics", highlight=False)
        if plot is not None:
            plot_trajectories(plot, {"estimate": est.poses}, title=f"{seq.root.name} (no ground truth)")
            console.print(f"plot written to {plot}", highlight=False)
        return
    stop = len(seq) if end is None else end
    g = gt.poses[start:stop]
    res = evaluate(Trajectory.from_poses(relative(g[0], g)), Trajectory.from_poses(est.poses), name=seq.root.name)
    for note in res.notes:
        console.print(f"[yellow]note[/] {note}", highlight=False)
    out.print(report_table(EvalReport([res], "none")))
    if plot is not None:
        plot_trajectories(plot, {"GT": res.gt_poses, label: res.est_poses},
                          title=f"{seq.root.name}: ATE {res.ate:.2f} m")
        console.print(f"plot written to {plot}", highlight=False)
