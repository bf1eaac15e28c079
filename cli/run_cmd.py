"""`d3lvo run`: the ONNX pipeline over a recording in any input format, poses written as they come,
and a results folder that holds everything about the run."""

from __future__ import annotations

import inspect
import math
import time
import typing
import warnings
from pathlib import Path

import numpy as np

import typer
from rich.table import Table

from d3lvo_deploy.errors import D3LVOInputError

from .common import console, friendly_errors, given_on_command_line, lead, note_oversubscribed, out
from .progress import frame_progress


def resolve_model_dir(onnx: Path | None) -> Path:
    if onnx is not None:
        return onnx
    from d3lvo_deploy.bundled import bundled_model_dir

    return bundled_model_dir()


def latency_table(summary) -> Table:
    """Per stage; the classical solve beside completion and encoder (`BESIDE_ROW`) is not in the
    total. Where the slowest frame is one of the first two, a caption says why (warm-up, and the
    first pair's cold start), lest it read as a stall a car would see every so often."""
    from d3lvo_deploy.odometry import BESIDE_ROW

    stats = summary.stats()
    total = summary.latencies_ms.get("total", [])
    # the first two frames timed: the engines warm up, and the first pair of a run started fresh
    # or resumed after one pose (no motion to start from) also tries the cold start's motions
    cold = getattr(summary, "resumed_from", 0) <= 1
    first = len(total) > 2 and int(np.argmax(total)) <= 1
    why = "the engines warming up" + ("; the first pair also tries the cold start's starting motions" if cold else "")
    t = Table(title="latency per frame (ms)", caption=f"max: one of the run's first frames ({why})" if first else None)
    for c in ("stage", "mean", "p90", "max"):
        t.add_column(c, justify="right")
    for k in ("read", "project", "completion", "encoder", BESIDE_ROW, "flowpose", "total"):
        if k in stats:
            s = stats[k]
            t.add_row(k, f"{s['mean']:.1f}", f"{s['p90']:.1f}", f"{s['max']:.1f}")
    return t


# the options a results folder's config.toml records and `--config` reads back: what decides the
# poses (where they are written, resume and pictures do not)
RUN_KEYS = ("path", "fmt", "calib", "image_topic", "cloud_topic", "info_topic", "max_dt", "gt", "onnx", "method",
            "start", "end", "provider", "threads", "backend", "ov_precision", "optimization", "realtime", "viz_every",
            "pipeline", "classical_beside", "max_accel")


# what belongs to the recording a config repeats: another recording given on the command line
# brings its own (its format guessed again, its topics, calibration and ground truth found beside it)
RECORDING_KEYS = ("fmt", "image_topic", "cloud_topic", "info_topic", "max_dt", "calib", "gt")


def throughput_line(summary) -> str:
    """Frames per second of wall time beside the per-frame latency: with the pipeline they differ."""
    total = summary.latencies_ms.get("total", [])
    if not total:
        return ""
    how = ("reading, projecting and encoding the next frame beside the flow+pose stage" if summary.deep
           else "reading and projecting the next frame beside the network" if summary.pipelined
           else "one frame at a time")
    return (f"throughput {summary.throughput:.1f} frames/s ({len(total)} frames in {summary.wall_s:.2f} s, {how}); "
            f"latency per frame median {float(np.median(total)):.1f} ms")


@friendly_errors
def run_command(
    ctx: typer.Context,
    path: Path | None = typer.Argument(None, help="The recording: a KITTI odometry sequence or raw drive, a ROS 1 "
                                       "/ ROS 2 bag (.bag, .mcap, .db3 or its folder), or a folder of images/ and "
                                       "scans/ (.pcd .ply .bin .npy) with calib.txt.", show_default=False),
    fmt: str = typer.Option("auto", "--format", help="Input format: auto (guessed from PATH) | kitti | kitti-raw | "
                            "rosbag | folder."),
    seq_dir: Path | None = typer.Option(None, "--seq-dir", help="Same as PATH (a KITTI odometry sequence folder)."),
    kitti_root: Path | None = typer.Option(None, "--kitti-root", help="KITTI odometry root (sequences/, poses/)."),
    sequence: str | None = typer.Option(None, "--sequence", help="Sequence id under --kitti-root, e.g. 09."),
    calib: Path | None = typer.Option(None, "--calib", help="Bags and folders: calibration file, K + T_cam_lidar "
                                      "(or KITTI's P2 + Tr); for a bag it replaces CameraInfo and /tf_static."),
    image_topic: str | None = typer.Option(None, "--image-topic", help="Bags: the Image/CompressedImage topic "
                                           "(needed when there are several)."),
    cloud_topic: str | None = typer.Option(None, "--cloud-topic", help="Bags: the PointCloud2 topic."),
    info_topic: str | None = typer.Option(None, "--info-topic", help="Bags: the CameraInfo topic (default: the "
                                          "one beside the image topic)."),
    max_dt: float = typer.Option(0.05, "--max-dt", help="Bags: an image and a scan further apart in time (s) are "
                                 "not paired."),
    out_dir: Path | None = typer.Option(None, "--out-dir", help="Results folder (default: results/<name>_<time>, "
                                        "with results/latest pointing at it); with --sequences, the folder for "
                                        "NN.txt trajectories."),
    out_path: Path | None = typer.Option(None, "--out", help="Write only this trajectory file instead of a results "
                                         "folder."),
    pose_fmt: str = typer.Option("kitti", "--pose-format", help="With --out: kitti | tum."),
    config: Path | None = typer.Option(None, "--config", help="Repeat a run: the config.toml of its results folder "
                                       "(options given on the command line take precedence)."),
    sequences: str | None = typer.Option(None, "--sequences", help="Many sequences under --kitti-root: 00-10 or 00,05."),
    engine: str = typer.Option("local", "--engine", help="With --sequences: sequential | local (processes) | ray."),
    workers: int = typer.Option(2, "--workers", help="With --sequences: parallel workers."),
    address: str | None = typer.Option(None, "--address", help="With --engine ray: cluster address (default: local)."),
    chunk: int = typer.Option(1000, "--chunk", help="With --sequences: frames per task (long sequences are split)."),
    overlap: int = typer.Option(2, "--overlap", help="With --sequences: frames shared by consecutive chunks (the "
                                "stitch anchors at the last one, so each chunk's cold-started first pair is dropped)."),
    onnx: Path | None = typer.Option(None, "--onnx", help="Exported model folder (default: the bundled model)."),
    start: int = typer.Option(0, "--start", help="First frame."),
    end: int | None = typer.Option(None, "--end", help="One past the last frame."),
    resume: bool = typer.Option(False, "--resume", help="Continue an interrupted run (name its --out-dir or --out)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace poses (and a --rerun recording) an earlier run "
                                   "left in the output."),
    viz: Path | None = typer.Option(None, "--viz", help="Folder for pictures of what the network sees (image, LiDAR "
                                    "and completed depth, flow, pose confidence), one PNG per --viz-every frames; "
                                    "a relative path lies inside the results folder."),
    viz_every: int = typer.Option(10, "--viz-every", help="With --viz or --rerun: pictures of every N-th frame."),
    rerun: Path | None = typer.Option(None, "--rerun", help="Write a Rerun recording (FILE.rrd: trajectory, LiDAR "
                                      "points, camera images and network outputs) for the Rerun viewer (the "
                                      "\\[rerun] extra); a relative path lies inside the results folder."),
    gt: Path | None = typer.Option(None, "--gt", help="Ground truth to score against (default: found beside the "
                                   "sequence, or a KITTI raw drive's OXTS)."),
    plot: Path | None = typer.Option(None, "--plot", help="Write the trajectory's top view to this PNG (default: a results "
                                     "folder's trajectory.png, when matplotlib is installed)."),
    provider: str = typer.Option("cpu", "--provider", help="cpu | cuda | tensorrt (falls back to cpu)."),
    threads: int = typer.Option(0, "--threads", help="Threads of every stage: the engines', and OpenCV's "
                                 "for --method direct (0: OMP_NUM_THREADS where set, else all cores)."),
    backend: str = typer.Option("auto", "--backend", help="onnxruntime | openvino (the \\[openvino] extra) | auto "
                                "(openvino where installed, else onnxruntime; `d3lvo bench` times both)."),
    ov_precision: str = typer.Option("f32", "--ov-precision", help="With --backend openvino: f32 | bf16 (bf16 uses "
                                     "the CPU's AVX512_BF16/AMX paths; see docs/performance.md)."),
    optimization: str = typer.Option("all", "--optimization", help="Graph optimisation: disable|basic|extended|all."),
    realtime: bool = typer.Option(False, "--realtime", help="Pace frames by their timestamps, like a live sensor."),
    pipeline: bool = typer.Option(False, "--pipeline/--no-pipeline", help="Read and project frame t+1 on a second "
                                  "thread while the network works on frame t (on onnxruntime also complete and encode it "
                                  "beside the flow+pose stage), which then takes one thread fewer (same poses; more "
                                  "frames/s, a little more latency: `d3lvo bench` prints both rates)."),
    method: str = typer.Option("d3lvo", "--method", help="d3lvo (the ONNX network) | direct (the no-learning "
                               "photometric LiDAR-visual tracker the network is measured against: the model's "
                               "own solver and point settings, every point weighted 1)."),
    classical_beside: bool = typer.Option(True, "--classical-beside/--no-classical-beside", help="With a model that "
                                          "has the classical stage (the bundled one) and two cores or more: solve the "
                                          "classical mode on a thread of its own while completion and encoder run, or "
                                          "in the flow+pose graph's batch (the same poses)."),
    max_accel: float = typer.Option(0.0, "--max-accel", help="The motion guard (either method): a solved motion whose "
                                    "speed differs from the last one's by more than this many m/s^2 times the time "
                                    "between the frames keeps the last motion instead (a car brakes at up to ~10 "
                                    "m/s^2; 30 was chosen on validation drives, and raises the error on some drives: "
                                    "docs/evaluation.md); 0, the default, turns it off."),
) -> None:
    """Estimate the trajectory of a recording with the ONNX stages (no torch needed).

    Example: d3lvo run drive.mcap   (results in results/drive_<time>/, results/latest points there)
    """
    opts = {k: v for k, v in locals().items() if k != "ctx"}
    if config is not None:
        opts = _apply_config(ctx, opts, config)
    note_oversubscribed(opts["threads"])
    _run(**opts)


def _apply_config(ctx: typer.Context, opts: dict, config: Path) -> dict:
    """The config's [run] values for every option not given on the command line."""
    from d3lvo_deploy.results import read_config

    table = read_config(config)
    unknown = sorted(set(table) - set(RUN_KEYS))
    if unknown:
        raise D3LVOInputError(config, f"unknown option {unknown[0]!r} in [run] (known: {', '.join(RUN_KEYS)})")
    given = lambda name: given_on_command_line(ctx, name)  # noqa: E731
    hints = typing.get_type_hints(inspect.unwrap(run_command))
    named = next((opts[k] for k in ("path", "seq_dir") if given(k)), None)
    if given("kitti_root") and opts.get("sequence"):
        named = Path(opts["kitti_root"]) / "sequences" / str(opts["sequence"])
    elif given("kitti_root"):
        named = Path(opts["kitti_root"])
    recorded = table.get("path")
    other = named is not None and not (isinstance(recorded, str) and Path(named).resolve() == Path(recorded).resolve())
    for k, v in table.items():
        if k == "path" and named is not None:
            continue  # the recording named on the command line
        if k in RECORDING_KEYS and other:
            continue  # another recording's own format, topics, calibration and ground truth
        if not given(k):
            opts[k] = _config_value(config, k, v, hints[k])
    _check_model(config, opts)
    return opts


def _config_value(config: Path, key: str, value, hint):
    """A [run] value as the option's type (a path from its string), or one error naming the key:
    a hand-edited `threads = "two"` would otherwise fail deep inside the run."""
    from d3lvo_deploy.config_values import converted, describe, fits

    kind = next((t for t in typing.get_args(hint) if t is not type(None)), hint)
    if not fits(value, kind):
        raise D3LVOInputError(config, f"[run] {key} = {value!r}: expected {describe(kind)}")
    return converted(value, kind)


def _check_model(config: Path, opts: dict) -> None:
    """A repeat on another model gives other poses: say so (the run itself goes ahead)."""
    from d3lvo_deploy.manifest import sha256_file
    from d3lvo_deploy.results import CONFIG, read_toml

    path = config / CONFIG if config.is_dir() else config
    model = read_toml(path).get("model")
    recorded = model.get("manifest_sha256") if isinstance(model, dict) else None
    manifest = resolve_model_dir(opts["onnx"]) / "manifest.json"
    if recorded and manifest.is_file() and sha256_file(manifest) != recorded:
        console.print(lead("warning", "yellow", f" {manifest} differs from the model {path} recorded "
                                                f"(sha256 {recorded[:12]}...): the poses will differ"), highlight=False)


def _open_recording(path, fmt, seq_dir, kitti_root, sequence, calib, gt, image_topic, cloud_topic, info_topic, max_dt):
    from d3lvo_deploy.datasets import BagOptions, open_sequence
    from d3lvo_deploy.sequence import KittiSequence

    given = [x for x in (path, seq_dir, kitti_root) if x is not None]
    if len(given) != 1:
        raise D3LVOInputError(None, "name one recording: PATH (or --seq-dir DIR, or --kitti-root R --sequence NN)")
    if kitti_root is not None:
        if sequence is None:
            raise D3LVOInputError(kitti_root, "--kitti-root needs --sequence (e.g. 09)")
        seq = KittiSequence.from_kitti_root(kitti_root, sequence)
        return KittiSequence.open(seq.root, gt=gt) if gt is not None else seq
    if not (max_dt >= 0 and math.isfinite(max_dt)):  # else reported as images that never pair
        raise D3LVOInputError(None, f"--max-dt must be a time of 0 s or more (the most an image and its scan may "
                                    f"be apart; 0: equal stamps), not {max_dt}")
    bag = BagOptions(image_topic=image_topic, cloud_topic=cloud_topic, info_topic=info_topic, max_dt=max_dt)
    return open_sequence(path if path is not None else seq_dir, fmt, gt=gt, calib=calib, bag=bag)


def _check_ground_truth(seq, given: bool) -> None:
    """A ground truth that cannot score the run (missing, unreadable, another length) is one error
    before the first frame, not after the last, where --gt named it; one found beside the recording
    (a `poses.txt` of the full drive beside some of its frames) is a warning, and the run goes on
    unscored."""
    try:
        seq.ground_truth  # noqa: B018 - reads and checks it (one pose per frame) where the recording has one
    except D3LVOInputError as e:
        if given or not hasattr(seq, "gt_path"):
            raise
        console.print(lead("warning", "yellow", f" {e}; the run goes on without scoring"), highlight=False)
        seq.gt_path = None


def _run(path, fmt, seq_dir, kitti_root, sequence, calib, image_topic, cloud_topic, info_topic, max_dt, out_dir,
         out_path, pose_fmt, config, sequences, engine, workers, address, chunk, overlap, onnx, start, end, resume,
         overwrite, viz, viz_every, rerun, gt, plot, provider, threads, backend, ov_precision, optimization, realtime,
         pipeline, method, classical_beside, max_accel) -> None:
    from d3lvo_deploy.motion_guard import MotionGuard
    from d3lvo_deploy.onnx_model import SessionConfig
    from d3lvo_deploy.pipeline import RunConfig, execute_run, prepare_run
    from d3lvo_deploy.results import CONFIG, ResultsFolder, default_folder, record_file

    if method not in ("d3lvo", "direct"):
        raise D3LVOInputError(None, f"--method must be d3lvo or direct, not {method!r}")
    if not (np.isfinite(max_accel) and max_accel >= 0):
        raise D3LVOInputError(None, f"--max-accel must be 0 (off) or a positive number of m/s^2, not {max_accel:g}")
    guard = MotionGuard(max_accel=float(max_accel))
    if out_path is not None and out_dir is not None:
        raise D3LVOInputError(None, "--out writes one trajectory file and --out-dir a results folder: name one of them")
    if out_path is None and pose_fmt.lower() != "kitti" and sequences is None:
        raise D3LVOInputError(None, f"--pose-format {pose_fmt} is for --out FILE; a results folder holds both "
                                    "poses.txt (KITTI) and poses_tum.txt (TUM)")
    if resume and overwrite:
        raise D3LVOInputError(None, "--resume continues the poses already written and --overwrite starts over: "
                                    "name one of them")
    if plot is not None:
        from d3lvo_deploy.extras import require

        require("matplotlib", what="--plot")
        from d3lvo_deploy.plot import plot_path

        plot = plot_path(plot)
    if sequences is not None:
        if method != "d3lvo":
            raise D3LVOInputError(None, "--sequences runs the network only; run --method direct per sequence")
        # what a single run takes and many sequences do not: refused rather than ignored
        single = {"--start": start != 0, "--end": end is not None, "--resume": resume, "--gt": gt is not None,
                  "--plot": plot is not None, "--viz": viz is not None, "--rerun": rerun is not None,
                  "--realtime": realtime, "--pipeline": pipeline, "--out": out_path is not None}
        if any(single.values()):
            raise D3LVOInputError(None, f"{', '.join(k for k, v in single.items() if v)}: for a single run; "
                                        "--sequences runs whole sequences from their start, scored against "
                                        "poses/NN.txt, into --out-dir")
        return _run_many(kitti_root, sequences, out_dir, onnx, engine, workers, address, chunk, overlap, backend,
                         guard, overwrite)
    if resume and out_path is None and out_dir is None:
        raise D3LVOInputError(None, "--resume continues a results folder: name it with --out-dir "
                                    "(results/latest is the newest)")
    shown: set[str] = set()  # the warnings printed, each once
    with warnings.catch_warnings(record=True) as caught:  # a reader's notes (an assumed frame rate), in one style
        warnings.simplefilter("always")
        seq = _open_recording(path, fmt, seq_dir, kitti_root, sequence, calib, gt, image_topic, cloud_topic,
                              info_topic, max_dt)
    _print_warnings(caught, shown)
    _check_ground_truth(seq, given=gt is not None)
    sc = SessionConfig(provider=provider, threads=threads, optimization=optimization, backend=backend,
                       ov_precision=ov_precision, classical_beside=classical_beside)
    sc.check()
    odometry, why, loading = None, "", "loading the model"
    if method == "direct":
        from d3lvo_deploy.direct import DirectConfig, DirectOdometry
        from d3lvo_deploy.manifest import load_manifest

        # the classical mode of the model the run would use (the bundled one by default): its
        # point selection and solver settings, with no learned confidence
        model_config = load_manifest(resolve_model_dir(onnx))["model_config"]
        odometry, model_dir = DirectOdometry(seq.calib, DirectConfig.of_model(model_config), guard), None
        if sc.engine_threads:  # --threads (or OMP_NUM_THREADS) for OpenCV's pyramids and gradients too
            import cv2

            cv2.setNumThreads(sc.engine_threads)
    else:
        from d3lvo_deploy.backends import choose_engine, openvino_compiled
        from d3lvo_deploy.manifest import load_manifest

        model_dir = resolve_model_dir(onnx)
        manifest = load_manifest(model_dir, verify_hashes=False)
        frames = (len(seq) if end is None else min(end, len(seq))) - start
        sc, why = choose_engine(sc, manifest, frames, pipelined=pipeline)
        if sc.backend == "openvino" and not openvino_compiled(sc.pipelined() if pipeline else sc, manifest):
            loading = "compiling the model for OpenVINO (the first time on this CPU only; cached for later runs)"
    if viz is not None and (method != "d3lvo" or viz_every < 1):
        raise D3LVOInputError(viz, "--viz shows the network's inputs and outputs: needs --method d3lvo and --viz-every >= 1")
    if rerun is not None and viz_every < 1:
        raise D3LVOInputError(rerun, "--viz-every must be at least 1")
    folder, fresh = None, False
    if out_path is None:  # the last step before the model loads: a refused argument leaves no folder
        fresh = out_dir is None
        folder = ResultsFolder(out_dir if out_dir is not None else default_folder(Path("results"), _name(seq)))
        out_path, pose_fmt = folder.poses, "kitti"
        viz = None if viz is None else (viz if viz.is_absolute() else folder.path / viz)
        rerun = None if rerun is None else (rerun if rerun.is_absolute() else folder.path / rerun)
    absolute = lambda p: None if p is None else Path(p).resolve()  # noqa: E731 - repeatable from anywhere
    record = dict(path=seq.root.resolve(), fmt=seq.format_name, calib=absolute(calib), image_topic=image_topic,
                  cloud_topic=cloud_topic, info_topic=info_topic, max_dt=max_dt, gt=absolute(gt), onnx=absolute(onnx),
                  method=method, start=start, end=end, provider=provider, max_accel=float(max_accel))
    record_path = folder.path / CONFIG if folder is not None else record_file(out_path)
    if resume:
        _check_resume(record_path, out_path, record, model_dir if model_dir is not None else resolve_model_dir(onnx))
    rc = RunConfig(out=out_path, fmt=pose_fmt, start=start, end=end, resume=resume, overwrite=overwrite,
                   realtime=realtime, viz_dir=viz, viz_every=viz_every, rerun_path=rerun, pipeline=pipeline,
                   guard=guard)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # every argument, the output file and the model are checked before the progress bar
        try:
            with console.status(loading):
                plan = prepare_run(seq, model_dir, rc, sc, odometry=odometry)
        except D3LVOInputError:
            if folder is not None and fresh:
                from d3lvo_deploy.results import remove_if_empty

                remove_if_empty(folder.path)
            raise
    _print_warnings(caught, shown)
    label = "D3LVO (ONNX)" if method == "d3lvo" else "direct tracker"
    engine_name = plan.odo.model.backend if method == "d3lvo" else "numpy"
    record.update(threads=sc.engine_threads,  # the count used
                  backend=engine_name if method == "d3lvo" else backend, ov_precision=ov_precision,
                  optimization=optimization, realtime=realtime, viz_every=viz_every, pipeline=pipeline,
                  classical_beside=classical_beside)
    if folder is not None:
        folder.create()
        if overwrite:  # an earlier run's outputs are not this run's, whether it finishes or not
            from d3lvo_deploy.results import LATENCY, METRICS

            for name in (METRICS, LATENCY):
                (folder.path / name).unlink(missing_ok=True)
    try:
        _write_config(record_path, record, model_dir if model_dir is not None else resolve_model_dir(onnx),
                      engine_name, seq, plan)
    except D3LVOInputError as e:
        if folder is not None:  # the results folder is the run's own: it must hold its config
            raise
        console.print(lead("warning", "yellow", f" {e}: --resume cannot check what it continues"), highlight=False)
    if folder is not None and fresh:
        from d3lvo_deploy.results import link_latest

        latest = folder.path.parent / "latest"
        if not link_latest(folder.path) and latest.exists() and not latest.is_symlink():
            console.print(lead("note", "yellow", f" {latest} is not the link d3lvo keeps to the newest run (a "
                                                 "folder or file of its own): left as it is"), highlight=False)
    if plan.finished:
        console.print(f"{out_path} already holds all {plan.n} poses of frames {plan.rc.start}..{plan.rc.end - 1}: "
                      "nothing to run (--overwrite starts over)", highlight=False)
        _finish(seq, folder, out_path, plan.rc.fmt, start, end, plot, label, None)
        return
    if method == "d3lvo":
        # a thread count the user did not type on this command line is named, with where it came from
        n = sc.engine_threads
        from_env = f"; {n} thread{'s' * (n != 1)} from OMP_NUM_THREADS" if not sc.threads and n else ""
        beside = "; its classical solve on a second thread beside completion and encoder" if plan.odo.model.beside else ""
        console.print(f"model {model_dir} on {engine_name} ({why}{from_env}{beside})", highlight=False)
    console.print(f"{seq.format_name} recording {seq.root}: {len(seq)} frames; "
                  f"poses in {seq.frame_label}", highlight=False)
    if plan.done.shape[0]:
        console.print(f"resuming after {len(plan.done)} poses already in {out_path}", highlight=False)
    with warnings.catch_warnings(record=True) as caught, frame_progress() as bar:
        warnings.simplefilter("always")
        task = bar.add_task("run", total=plan.n, rate="")
        first: list = []  # (frames done, time) at the first frame: the rate is frames since over time since

        def tick(done: int, total: int, ms: float) -> None:
            now = time.perf_counter()
            if not first:
                first.append((done, now))
            n, t = done - first[0][0], now - first[0][1]
            bar.update(task, completed=done, total=total, rate=f"{n / t:.1f} frames/s" if n and t > 0 else "")

        try:
            summary = execute_run(plan, progress=tick)
        except KeyboardInterrupt:
            bar.stop()
            again = f"--out-dir {folder.path}" if folder is not None else ""
            console.print(lead("interrupted", "yellow", f": the poses so far are in {out_path}; the same command with "
                                                        f"--resume {again} continues from there"), highlight=False)
            raise typer.Exit(130) from None
    _print_warnings(caught, shown)
    out.print(latency_table(summary))
    out.print(throughput_line(summary), highlight=False)
    out.print(f"{summary.frames} poses in {out_path} ({plan.rc.fmt}, {seq.frame_label}, first pose identity)",
              highlight=False)
    if summary.guarded:
        out.print(guard_line(summary.guarded, summary.frames - max(summary.resumed_from, 1), max_accel), highlight=False)
    rrd = plan.rc.rerun_path
    if rrd is not None and (folder is None or Path(rrd).parent.resolve() != folder.path.resolve()):
        console.print(f"Rerun recording in {rrd} (open it with: rerun {rrd})", highlight=False)  # else the folder's list
    _finish(seq, folder, out_path, plan.rc.fmt, start, end, plot, label, summary)


def guard_line(guarded: int, pairs: int, max_accel: float) -> str:
    return (f"motion guard: the previous motion kept on {guarded} of {pairs} pairs, where the solved speed changed "
            f"by more than {max_accel:g} m/s^2 (--max-accel)")


def _name(seq) -> str:
    root = seq.root
    name = root.stem if root.is_file() else root.name
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "run"


def _run_tables(record: dict, model_dir: Path) -> dict[str, dict]:
    """The [run] and [model] tables of a run's config, as written and as --resume compares them."""
    from d3lvo_deploy.manifest import sha256_file

    return {"run": {k: (str(v) if isinstance(v, Path) else v) for k, v in record.items()},
            "model": {"dir": str(model_dir.resolve()), "manifest_sha256": sha256_file(model_dir / "manifest.json")}}


def _check_resume(record_path: Path, out_path: Path, record: dict, model_dir: Path) -> None:
    """Poses already in the output belong to the run this command repeats, or --resume stops here."""
    from d3lvo_deploy.results import check_resume

    if not out_path.is_file() or out_path.stat().st_size == 0:
        return
    if record_path.is_file():
        check_resume(record_path, _run_tables(record, model_dir), out_path)
    else:
        console.print(lead("warning", "yellow", f" {record_path}: missing, so nothing shows that the poses in {out_path} "
                                                "are of this recording, frames and model; they are continued as if "
                                                "they were"), highlight=False)


def _write_config(path: Path, record: dict, model_dir: Path, engine_name: str, seq, plan=None) -> None:
    """The run's config.toml (a results folder's, or the one beside an --out trajectory)."""
    import os
    import platform

    from d3lvo_deploy import __version__
    from d3lvo_deploy.cpu import cpu_info
    from d3lvo_deploy.results import to_toml

    cpu = cpu_info()
    tables = {
        **_run_tables(record, model_dir),
        "machine": {"engine": engine_name, "engine_version": _engine_version(engine_name), "cpu": cpu.line(),
                    "python": platform.python_version(), "d3lvo_deploy": __version__},
        "recording": {"frames": len(seq), "pose_frame": seq.frame_label},
    }
    if plan is not None and plan.sc is not None:  # the threads each stage ran on (0: the engine's choice)
        model = plan.odo.model
        stages = [s for s in ("completion", "encoder", "classical") if s in model.sessions] + ["flowpose"]
        tables["machine"].update(pipeline_depth=plan.depth, **{f"{s}_threads": model.threads(s) for s in stages},
                                 prepare_threads=plan.sc.preparing_threads, classical_beside=model.beside)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text("# d3lvo run --config THIS_FILE repeats the run: the [run] table holds its options\n"
                       + to_toml(tables))
        os.replace(tmp, path)
    except OSError as e:
        raise D3LVOInputError(path, f"cannot write the run's config ({e.strerror})") from None


def _engine_version(engine_name: str) -> str:
    if engine_name == "openvino":
        import openvino

        return openvino.__version__
    if engine_name == "onnxruntime":
        import onnxruntime

        return onnxruntime.__version__
    return "numpy " + np.__version__


def _finish(seq, folder, out_path: Path, fmt: str, start: int, end: int | None, plot: Path | None, label: str,
            summary) -> None:
    """Score the run where there is ground truth; in a results folder, also the TUM copy, the
    metrics, the latency and the plot; then say what was written where."""
    from d3lvo_deploy.results import LATENCY, METRICS, PLOT, latency_report

    written = [out_path]
    if folder is not None:
        written.append(folder.write_tum(seq.times, start))
        if summary is not None:
            written.append(folder.write_json(LATENCY, latency_report(summary)))
        if plot is None:
            from d3lvo_deploy.extras import installed

            plot = folder.path / PLOT if installed("matplotlib") else None
    res = _score(seq, out_path, fmt, start, end, plot, label)
    if folder is not None:
        if res is not None:
            written.append(folder.write_json(METRICS, res.to_dict()))
        written.append(folder.path / "config.toml")
        if plot is not None:
            written.append(plot)
        # a --plot elsewhere by its path: the folder does not hold it
        named = [p.name if p.parent.resolve() == folder.path.resolve() else str(p) for p in written if p.exists()]
        console.print(f"results in {folder.path}: " + ", ".join(named)
                      + _asked(folder), highlight=False)


def _asked(folder) -> str:
    extra = [p.name + ("/" if p.is_dir() else "") for p in sorted(folder.path.iterdir())
             if p.is_dir() or p.suffix == ".rrd"]
    return (", " + ", ".join(extra)) if extra else ""


SCAN_WARNINGS_SHOWN = 5  # of a run's per-frame scan warnings; the rest are counted


def _print_warnings(caught, seen: set[str]) -> None:
    """Each message once per command (`seen`: what its earlier steps printed), and at most
    SCAN_WARNINGS_SHOWN of the per-frame scan warnings."""
    from d3lvo_deploy.odometry import ScanWarning

    scans = 0
    for w in caught:
        msg = str(w.message)
        if msg in seen:
            continue
        seen.add(msg)
        if issubclass(w.category, ScanWarning):
            scans += 1
            if scans > SCAN_WARNINGS_SHOWN:
                continue
        console.print(lead("warning", "yellow", f" {msg}"), highlight=False)
    if scans > SCAN_WARNINGS_SHOWN:
        console.print(lead("warning", "yellow", f" and {scans - SCAN_WARNINGS_SHOWN} more scan warnings, one per "
                                                "frame, not shown"), highlight=False)


def _run_many(kitti_root, spec, out_dir, onnx, engine, workers, address, chunk, overlap, backend, guard,
              overwrite: bool = False) -> None:
    import os
    import time

    from d3lvo_deploy.backends import SessionConfig

    from d3lvo_deploy.evaluation import evaluate_files
    from d3lvo_deploy.scaleout import check_engine, parse_sequences, run_many

    from .eval_cmd import report_table

    if kitti_root is None or out_dir is None:
        raise D3LVOInputError(None, "--sequences needs --kitti-root R and --out-dir OUT")
    check_engine(engine, workers)
    names = parse_sequences(spec)
    dirs = {n: kitti_root / "sequences" / n for n in names}
    for n, d in dirs.items():
        if not d.is_dir():
            raise D3LVOInputError(d, f"sequence {n} not found under {kitti_root}")
    held = [out_dir / f"{n}.txt" for n in names if (out_dir / f"{n}.txt").is_file()]
    if held and not overwrite:  # as a single run's --out: never replaced without being asked
        raise D3LVOInputError(held[0], f"already holds poses from an earlier run ({len(held)} of the {len(names)} "
                                       "sequences' files are there); --overwrite replaces them, or give another "
                                       "--out-dir")
    from d3lvo_deploy.sequence import KittiSequence
    from d3lvo_deploy.scaleout import plan_chunks

    seqs = {n: KittiSequence.open(d) for n, d in dirs.items()}
    total = sum(len(plan_chunks(len(s), chunk, overlap)) for s in seqs.values())
    # ground truth checked before the work, as a single run's: one that does not fit is a warning
    # and its sequence goes unscored; the others are still scored
    scored, misfit = [], []
    for n, s in seqs.items():
        try:
            if s.ground_truth is not None:
                scored.append(n)
        except D3LVOInputError as e:
            console.print(lead("warning", "yellow", f" {e}; sequence {n} runs without scoring"), highlight=False)
            misfit.append(n)
    # the machine's cores split between the workers, on the engine --backend names (resolved here,
    # so every worker runs the same one)
    sc = SessionConfig(threads=max(1, (os.cpu_count() or 1) // max(workers, 1)), backend=backend)
    sc.check()
    sc = sc.resolved()
    t0 = time.perf_counter()
    with frame_progress() as bar:
        task = bar.add_task(f"{engine} x{workers}", total=total, rate="chunks")
        residuals = run_many(dirs, resolve_model_dir(onnx), out_dir, engine=engine, workers=workers, chunk=chunk,
                             overlap=overlap, address=address, sc=sc, on_chunk=lambda c: bar.advance(task), guard=guard,
                             on_sequence=lambda n, p, r: console.print(f"{n}: {p} (overlap residual {r:.1e} m)",
                                                                         highlight=False))
    console.print(f"{len(residuals)} sequences in {time.perf_counter() - t0:.1f} s", highlight=False)
    absent = [n for n in names if n not in scored and n not in misfit]
    for what, which in (("ground truth that does not fit", misfit), ("no ground truth", absent)):
        if which:
            console.print(f"not scored ({what}): {', '.join(which)}", highlight=False)
    pairs = [(seqs[n].gt_path, out_dir / f"{n}.txt") for n in scored]
    if pairs:
        out.print(report_table(evaluate_files(pairs)))


def _score(seq, out_path: Path, fmt: str, start: int, end: int | None, plot: Path | None, label: str):
    from d3lvo_deploy.evaluation import EvalReport, evaluate
    from d3lvo_deploy.geometry import relative
    from d3lvo_deploy.plot import plot_trajectories
    from d3lvo_deploy.poses import Trajectory, read_poses

    from .eval_cmd import report_table

    est = read_poses(out_path, fmt)
    gt = seq.ground_truth
    if gt is None or len(est) < 2:  # no ground truth, or a run of one frame: nothing to score
        why = "no ground truth for this sequence" if gt is None else \
            f"{len(est)} pose: too few to score against the ground truth (2 at least)"
        console.print(f"{why}: no metrics", highlight=False)
        if plot is not None:
            plot_trajectories(plot, {"estimate": est.poses}, title=f"{seq.root.name} (not scored)")
            console.print(f"plot written to {plot}", highlight=False)
        return None
    stop = len(seq) if end is None else end
    g = gt.poses[start:stop]
    res = evaluate(Trajectory.from_poses(relative(g[0], g)), Trajectory.from_poses(est.poses), name=seq.root.name)
    for note in res.notes:
        console.print(lead("note", "yellow", f" {note}"), highlight=False)
    out.print(report_table(EvalReport([res], "none")))
    if plot is not None:
        plot_trajectories(plot, {"GT": res.gt_poses, label: res.est_poses},
                          title=f"{seq.root.name}: ATE {res.ate:.2f} m")
        console.print(f"plot written to {plot}", highlight=False)
    return res
