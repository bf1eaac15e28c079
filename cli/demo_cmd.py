"""`d3lvo demo`: the bundled model on a held-out synthetic sequence (scored) and on real KITTI frames."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import typer

from .common import console, friendly_errors, lead, out
from .progress import frame_progress

DEMO_SEED = 909  # not among the training seeds (10-18) nor validation seeds (109-110)
DEMO_FRAMES = 220  # ~140 m: long enough for the devkit's 100 m segments
DEMO_SIZE = (620, 188)  # the bundled model runs at 608x176; rendering at this size keeps the demo quick


@friendly_errors
def demo_command(
    out_dir: Path = typer.Option(Path(tempfile.gettempdir()) / "d3lvo-demo", "--out",
                                 help="Folder for the sequence, poses and plots (default: outside the checkout)."),
    frames: int = typer.Option(DEMO_FRAMES, "--frames", help="Length of the held-out synthetic sequence."),
    onnx: Path | None = typer.Option(None, "--onnx", help="Model folder (default: the bundled model)."),
) -> None:
    """Generate a held-out synthetic drive, run the ONNX pipeline, score it; then the real frames.

    Example: d3lvo demo --out /tmp/d3lvo-demo
    """
    from d3lvo_deploy.extras import require

    require("embreex", "matplotlib", what="d3lvo demo (it renders a drive and plots it)")
    from d3lvo_deploy.direct import DirectConfig, DirectOdometry
    from d3lvo_deploy.evaluation import EvalReport, evaluate
    from d3lvo_deploy.manifest import load_manifest
    from d3lvo_deploy.pipeline import RunConfig, run_sequence
    from d3lvo_deploy.plot import plot_trajectories
    from d3lvo_deploy.poses import read_poses
    from d3lvo_deploy.sequence import KittiSequence
    from d3lvo_deploy.synth.generator import SynthConfig, check_config, generate
    from d3lvo_deploy.bundled import bundled_model_dir, find_real_frames

    from .eval_cmd import _fmt, report_table
    from .run_cmd import latency_table, resolve_model_dir

    t_start = time.perf_counter()
    model_dir = resolve_model_dir(onnx)
    load_manifest(model_dir, verify_hashes=False)  # a wrong --onnx is one error before any rendering
    seq_dir = out_dir / "synthetic_heldout"
    cfg = SynthConfig(frames=frames, seed=DEMO_SEED, width=DEMO_SIZE[0], height=DEMO_SIZE[1])
    check_config(cfg)
    if _rendered(seq_dir, cfg):
        console.print(lead("1/3", "bold", f" reusing the held-out synthetic drive rendered earlier in {seq_dir}"),
                      highlight=False)
    else:
        console.print(lead("1/3", "bold", f" rendering a held-out synthetic drive ({frames} frames, seed {DEMO_SEED}) "
                                          f"into {seq_dir}"), highlight=False)
        with frame_progress() as bar:
            task = bar.add_task("synth", total=frames, rate="")
            generate(seq_dir, cfg, progress=lambda n: bar.update(task, completed=n), resume=False)

    from d3lvo_deploy.backends import SessionConfig

    sc = SessionConfig(backend="auto").resolved()  # OpenVINO where installed: the faster engine here
    engine = {"onnxruntime": "ONNX Runtime", "openvino": "OpenVINO"}[sc.backend]
    console.print(lead("2/3", "bold", f" D3LVO ({engine}, {'bundled model' if onnx is None else model_dir}) on it"),
                  highlight=False)
    seq = KittiSequence.open(seq_dir)
    poses_path = out_dir / "synthetic_heldout_poses.txt"
    with frame_progress() as bar:
        task = bar.add_task("run", total=len(seq), rate="")
        summary = run_sequence(seq, model_dir, RunConfig(out=poses_path, overwrite=True), sc,
                               progress=lambda n, tot, ms: bar.update(task, completed=n, rate=f"{ms:.0f} ms a frame"))
    res = evaluate(seq.ground_truth, read_poses(poses_path), name="synthetic held-out")
    # the baseline beside it: the model's classical mode, the same solver with every point weighted 1
    direct_path = out_dir / "synthetic_heldout_direct.txt"
    with frame_progress() as bar:
        task = bar.add_task("direct", total=len(seq), rate="")
        run_sequence(seq, None, RunConfig(out=direct_path, overwrite=True),
                     odometry=DirectOdometry(seq.calib, DirectConfig.of_model(load_manifest(model_dir)["model_config"])),
                     progress=lambda n, tot, ms: bar.update(task, completed=n, rate=f"{ms:.0f} ms a frame"))
    base = evaluate(seq.ground_truth, read_poses(direct_path), name="synthetic held-out")
    out.print(report_table({"D3LVO (ONNX)": EvalReport([res], "none"),
                            "--method direct (no learning)": EvalReport([base], "none")}))
    out.print(latency_table(summary))
    plot = plot_trajectories(out_dir / "synthetic_heldout.png", {"GT": res.gt_poses, "D3LVO (ONNX)": res.est_poses,
                                                                 "--method direct": base.est_poses},
                             title=f"held-out synthetic drive: t_rel {_fmt(res.t_rel)} % (direct {_fmt(base.t_rel)} %), "
                                   f"ATE {res.ate:.2f} m")
    console.print(f"poses: {poses_path} (--method direct: {direct_path.name})\nplot:  {plot}", highlight=False)

    real = find_real_frames()
    if real is None:
        console.print(lead("3/3", "bold", " ../shared/data (real KITTI frames) not found: skipped"), highlight=False)
    else:
        console.print(lead("3/3", "bold", f" the 20 real KITTI frames in {real}"), highlight=False)
        rseq = KittiSequence.open(real)
        rpath = out_dir / "real_r0926_poses.txt"
        run_sequence(rseq, model_dir, RunConfig(out=rpath, overwrite=True), sc)
        rp = read_poses(rpath).poses
        dist = float(np.linalg.norm(np.diff(rp[:, :3, 3], axis=0), axis=1).sum())
        rplot = plot_trajectories(out_dir / "real_r0926.png", {"D3LVO (ONNX)": rp}, title="real KITTI 2011_09_26 (no GT)")
        end = ", ".join(f"{v:.2f}" for v in rp[-1, :3, 3])
        out.print(f"real frames: {len(rp)} poses, a {dist:.2f} m path estimated, ending at ({end}) m in cam0 "
                  "(docs/evaluation.md compares it with LiDAR-only odometry). No ground truth "
                  "exists for these frames, so no accuracy is claimed"
                  + ("; the bundled model was trained on synthetic data only and is not meant for real KITTI "
                     "accuracy." if Path(model_dir).resolve() == bundled_model_dir().resolve() else "."),
                  highlight=False)
        console.print(f"poses: {rpath}\nplot:  {rplot}", highlight=False)
    size = sum(f.stat().st_size for f in out_dir.rglob("*") if f.is_file()) / 1e6
    console.print(f"demo finished in {time.perf_counter() - t_start:.0f} s; {out_dir} holds {size:.0f} MB "
                  "(delete it when done)", highlight=False)


def _rendered(seq_dir: Path, cfg) -> bool:
    """Whether seq_dir already holds this exact drive, every frame written."""
    from d3lvo_deploy.synth.generator import rendered_settings

    # a synth.json missing or unreadable: not this drive, rendered again
    return (rendered_settings(seq_dir) == cfg.as_written() and (seq_dir / "poses.txt").is_file()
            and len(list((seq_dir / "image_2").glob("*.png"))) == cfg.frames)
