"""`d3lvo synth`: a synthetic KITTI-format sequence from the procedural street world."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from d3lvo_deploy.errors import D3LVOInputError

from .common import console, friendly_errors
from .progress import frame_progress


def parse_size(size: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise D3LVOInputError(None, f"--size must look like 1241x376, not {size!r}") from None
    return w, h


@friendly_errors
def synth_command(
    out: Path = typer.Option(..., "--out", help="Output sequence folder (KITTI odometry layout)."),
    frames: int = typer.Option(100, "--frames", help="Number of frames (10 Hz)."),
    seed: int = typer.Option(0, "--seed", help="World and motion seed; same seed, same data."),
    motion_from: Path | None = typer.Option(None, "--motion-from", help="Replay a real KITTI GT trajectory file."),
    motion_start: int = typer.Option(0, "--motion-start", help="First GT frame to replay."),
    size: str = typer.Option("1241x376", "--size", help="Image size WxH (intrinsics scale with it)."),
    depth: bool = typer.Option(True, "--depth/--no-depth", help="Also write the renderer's dense depth (depth_2/)."),
    resume: bool = typer.Option(True, "--resume/--overwrite", help="Keep frames already written by an interrupted run."),
    traffic: float = typer.Option(0.0, "--traffic", help="Moving vehicles per 100 m of road (lead car, overtaking, "
                                  "overtaken, oncoming, crossing), with motion_2/ masks and the true flow_2/; "
                                  "0 renders a static street."),
    sensor_effects: bool = typer.Option(False, "--sensor-effects/--clean", help="Per-frame exposure changes, "
                                        "vignetting, shot noise and LiDAR dropout on dark or far surfaces."),
    ego_collisions: bool = typer.Option(False, "--ego-collisions", help="With --traffic: keep vehicles whose "
                                        "schedule runs into the camera's own car (dropped by default), as the "
                                        "bundled model's training drives were rendered (scripts/train_default.sh)."),
) -> None:
    """Render a synthetic KITTI-format sequence: image_2, velodyne, calib, times and GT poses.

    Example: d3lvo synth --out runs/data/traffic_09 --frames 200 --size 620x188 --traffic 3 --sensor-effects
    """
    from d3lvo_deploy.extras import require

    require("embreex", what="d3lvo synth")
    from d3lvo_deploy.synth.generator import (SynthConfig, check_config, check_output, frames_to_render, generate,
                                              make_poses)

    width, height = parse_size(size)
    if motion_from is not None and not motion_from.is_file():
        raise D3LVOInputError(motion_from, "trajectory to replay not found")
    cfg = SynthConfig(frames=frames, seed=seed, width=width, height=height,
                      motion_from=str(motion_from) if motion_from else None, motion_start=motion_start,
                      write_depth=depth, traffic=traffic, sensor_effects=sensor_effects, ego_collisions=ego_collisions)
    check_config(cfg)
    check_output(out, cfg, resume)  # before the progress bar: a refusal is one line
    make_poses(cfg)  # reads --motion-from (a fraction of a second)
    t0 = time.perf_counter()
    with frame_progress() as bar:
        task = bar.add_task("synth", total=frames, rate="")

        def tick(done: int) -> None:
            dt = time.perf_counter() - t0
            bar.update(task, completed=done, rate=f"{done / dt:.2f} frames/s" if dt > 0 else "")

        todo = frames_to_render(out, cfg, resume)
        generate(out, cfg, progress=tick, resume=resume)
    took = f"in {time.perf_counter() - t0:.1f} s"
    if todo == frames:
        console.print(f"wrote {frames} frames to {out} {took}", highlight=False)
    elif todo:
        kept = frames - todo
        console.print(f"wrote {todo} frame{'s' * (todo > 1)} to {out} {took}; the other {kept} "
                      f"{'were' if kept > 1 else 'was'} there", highlight=False)
    else:
        console.print(f"{out} holds all {frames} frames of these settings already: nothing rendered", highlight=False)
