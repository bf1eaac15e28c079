"""`d3lvo train`: train D3LVO on KITTI-format sequences (works under torchrun for DDP)."""

from __future__ import annotations

import os
from pathlib import Path

import typer

from d3lvo_deploy.errors import D3LVOInputError

from .common import console, friendly_errors, given_on_command_line, lead
from .progress import frame_progress


def baseline_line(m: dict) -> str:
    """Pair errors next to their baselines (models.train.pair_metrics): what 'learned' rests on."""
    parts = [f"flow EPE {k[len('flow_epe_'):]} {m[k]:.3f} (zero flow {m[k + '_zero']:.3f})"
             for k in sorted(m) if k.startswith("flow_epe_") and not k.endswith("_zero")]
    parts.append(f"rotation {m['rot_err_deg']:.4f} deg (no rotation {m['rot_err_deg_zero']:.4f})")
    parts.append(f"translation {m['trans_err_m']:.4f} m (no motion {m['trans_err_m_zero']:.4f})")
    # on drives with motion masks: how well low confidence ranks moving cells (uniform scores 0.5)
    parts += [f"{what} AUROC {k.rsplit('_', 1)[-1]} {m[k]:.4f} (uniform 0.5)"
              for what in ("moving", "shadow") for k in sorted(m) if k.startswith(f"{what}_auroc_")]
    return ", ".join(parts)


@friendly_errors
def train_command(
    ctx: typer.Context,
    data: list[Path] = typer.Option([], "--data", help="Training sequence folder (repeat for several)."),
    out: Path | None = typer.Option(None, "--out", help="Checkpoint path (written atomically every --ckpt-every "
                                    "steps; the resolved config is written beside it as OUT.toml)."),
    config: Path | None = typer.Option(None, "--config", help="TOML with \\[model] (preset and any width, level or "
                                       "solver field), \\[train], \\[loss], \\[augment]; command-line options win "
                                       "(docs/training.md)."),
    val: list[Path] = typer.Option([], "--val", help="Validation sequence folder (repeatable)."),
    steps: int = typer.Option(1000, "--steps", help="Optimizer steps in all (a resumed run counts from where it was)."),
    resume: Path | None = typer.Option(None, "--resume", help="Continue from this checkpoint."),
    stop_at: int | None = typer.Option(None, "--stop-at", help="Stop after this step, saving a checkpoint, while the "
                                       "learning-rate schedule still spans --steps (a long run in parts)."),
    mode: str = typer.Option("rgb_completion", "--mode", help="rgb | rgb_sparse | rgb_completion."),
    completion: str = typer.Option("learned", "--completion", help="learned | ipbasic."),
    preset: str = typer.Option("default", "--preset", help="default (the realtime network, 1216x352) | small (the same "
                               "at 608x176, CPU) | paper (as the paper sizes it: flow at 4 levels, MLP head; GPU)."),
    pose_head: str = typer.Option("auto", "--pose-head", help="points (the direct solver on the LiDAR points under "
                                  "a learned confidence; the bundled model's) | gauss_newton (on the network's cells; "
                                  "auto where there is depth) | mlp (the paper's regression) | auto."),
    init: Path | None = typer.Option(None, "--init", help="Start from this checkpoint's weights where names and "
                                     "shapes match (e.g. the bundled model's encoder and flow for a new pose head)."),
    batch_size: int = typer.Option(4, "--batch-size", help="Frame pairs per step."),
    lr: float = typer.Option(3e-4, "--lr", help="AdamW learning rate after warm-up (cosine decay to 5 %)."),
    val_every: int = typer.Option(500, "--val-every", help="Steps between validations on --val (the best is kept "
                                  "as OUT.best.pt)."),
    ckpt_every: int = typer.Option(100, "--ckpt-every", help="Steps between checkpoints (to --resume from)."),
    seed: int = typer.Option(0, "--seed", help="Seed of weights, sampling and augmentation."),
    device: str = typer.Option("auto", "--device", help="auto | cpu | cuda."),
    precision: str = typer.Option("fp32", "--precision", help="fp32 | bf16 (autocast on CPU and GPU) | fp16 (GPU, "
                                  "with a gradient scaler); the pose solvers always run in fp32."),
    workers: int = typer.Option(0, "--workers", help="DataLoader worker processes."),
    depth_cache: Path | None = typer.Option(None, "--depth-cache", help="Folder that keeps each frame's projected "
                                            "depth and solver points after the first epoch (faster loading)."),
    solver_loss: float = typer.Option(0.0, "--solver-loss", help="The point head: weight of the pose loss through "
                                      "the Gauss-Newton solver into the confidence (0: motion masks only; turns off "
                                      "flip and rotation augmentation, which the solver's images do not get)."),
    solver: list[str] = typer.Option([], "--set", help="Solver setting without weights, KEY=VALUE (pt_iters, "
                                     "pt_capacity, pt_min_gradient, pt_stop, pt_damping, pt_scale_every, pt_median_stride, pt_refine, pt_affine, pt_fine_restart, pt_restart_depth, pt_scan_gate, pt_conf_power, pt_gate, pt_conf_full, pt_select, pt_select_rotation, pt_select_unexplained, pt_select_scan, pt_select_scan_pass, pt_select_share, pt_classical_chain, pt_select_hold; gn_points, "
                                     "gn_iters, gn_huber, gn_damping, gn_lidar_pool); repeatable; may differ from "
                                     "the checkpoint's on --resume."),
) -> None:
    """Train D3LVO; reports loss, and t_rel/r_rel/ATE on --val sequences through the evaluator, with flow, rotation and translation errors beside their baselines (zero flow, no motion).

    The loss goes negative, and that is expected: eq. 11 adds the learnable balance terms s_t and s_q themselves (l = |dt| exp(-s_t) + s_t + |dq|^2 exp(-s_q) + s_q), and s_q settles near log(rotation error^2), about -9 for frame-to-frame motion.

    Example: d3lvo train --data runs/data/tr_00 --val runs/data/val_traffic --out runs/points.pt --preset small --pose-head points --steps 2000
    """  # noqa: E501 (typer keeps a docstring's line breaks in --help)
    opts = {k: v for k, v in locals().items() if k != "ctx"}
    file: dict = {"model": {}, "train": {}, "loss": {}, "augment": {}}
    from_file: set[str] = set()
    if config is not None:
        file, from_file = _apply_config(ctx, opts, config)
    if opts["resume"] is not None:
        _continue_as_trained(ctx, opts, from_file)
    _train(file=file, **opts)


def _continue_as_trained(ctx: typer.Context, opts: dict, from_file: set[str]) -> None:
    """A bare `--resume ck.pt` continues the checkpoint's model: its mode, completion and pose
    head where neither the command line nor the config names them (their defaults would be
    another model, refused)."""
    from d3lvo_deploy.extras import require

    require("torch", what="d3lvo train")
    from models.checkpoint import load_checkpoint

    trained = load_checkpoint(opts["resume"])["config"]
    for name in ("mode", "completion", "pose_head"):
        if not given_on_command_line(ctx, name) and name not in from_file:
            opts[name] = getattr(trained, name)


# [train] / [model] / [loss] keys that are also command-line options: (table, key) -> option
FILE_OPTIONS = {("train", "data"): "data", ("train", "out"): "out", ("train", "val"): "val",
                ("train", "steps"): "steps", ("train", "stop_at"): "stop_at", ("train", "batch_size"): "batch_size",
                ("train", "lr"): "lr", ("train", "val_every"): "val_every", ("train", "ckpt_every"): "ckpt_every",
                ("train", "seed"): "seed", ("train", "device"): "device", ("train", "num_workers"): "workers",
                ("train", "depth_cache"): "depth_cache",
                ("train", "init"): "init", ("train", "precision"): "precision", ("model", "preset"): "preset",
                ("model", "mode"): "mode", ("model", "completion"): "completion", ("model", "pose_head"): "pose_head",
                ("loss", "solver_pose_weight"): "solver_loss"}


def _apply_config(ctx: typer.Context, opts: dict, config: Path) -> tuple[dict, set[str]]:
    """File values for the options not given on the command line; returns the file's other keys
    and the options the file set."""
    from models.train_config import read_train_config

    file = read_train_config(config)
    given = lambda name: given_on_command_line(ctx, name)  # noqa: E731
    if given("preset") and opts["preset"] != file["model"].get("preset"):
        # another preset is another model (a file that names none, e.g. one a training wrote, is
        # read as sizes and levels of its own): the file's model fields make way, said by name
        dropped = sorted(k for k in file["model"] if k not in ("preset", "mode", "completion", "pose_head"))
        if dropped:
            console.print(lead("note", "yellow", f" --preset {opts['preset']} replaces {config}'s [model] "
                                                 f"{', '.join(dropped)}"), highlight=False)
        file["model"] = {k: v for k, v in file["model"].items() if k in ("mode", "completion", "pose_head")}
    if given("resume"):  # a resumed run takes its weights from the checkpoint, never from init
        file["train"].pop("init", None)
    if not given("out") and not given("resume") and file["train"].get("out") and Path(file["train"]["out"]).exists():
        raise D3LVOInputError(config, f"its out {file['train']['out']} exists already: --out NEW repeats the "
                                      f"training elsewhere, --resume {file['train']['out']} continues it")
    set_here = set()
    for (table, key), name in FILE_OPTIONS.items():
        if key not in file[table]:
            continue
        value = file[table].pop(key)
        if not given(name):
            if key in ("data", "val"):
                value = [Path(v) for v in value]
            elif key in ("out", "init", "depth_cache") and value is not None:
                value = Path(value)
            opts[name] = value
            set_here.add(name)
    return file, set_here


def _train(data, out, config, val, steps, resume, stop_at, mode, completion, preset, pose_head, init, batch_size, lr,
           val_every, ckpt_every, seed, device, precision, workers, depth_cache, solver_loss, solver, file) -> None:
    from d3lvo_deploy.extras import require

    require("torch", what="d3lvo train")
    from dataclasses import fields, replace

    from models.checkpoint import load_checkpoint
    from models.config import SOLVER_KEYS
    from models.data import AugmentConfig
    from models.loss import LossConfig
    from models.train import BATCH_NORMS, TrainConfig, TrainingInterrupted, best_path, train
    from models.train_config import model_config

    from .export_cmd import solver_settings

    if file["train"].get("batch_norm", "sync") not in BATCH_NORMS:
        raise D3LVOInputError(config, f"[train] batch_norm must be one of {', '.join(BATCH_NORMS)}, "
                                      f"not {file['train']['batch_norm']!r}")
    if not data:
        raise D3LVOInputError(config, "give training sequences: --data DIR (repeatable) or data = [...] in [train]")
    if out is None:
        raise D3LVOInputError(config, "give the checkpoint to write: --out FILE.pt or out = '...' in [train]")
    if precision not in ("fp32", "bf16", "fp16"):
        raise D3LVOInputError(None, f"--precision must be fp32, bf16 or fp16, not {precision!r}")
    _check_numbers(steps=steps, stop_at=stop_at, batch_size=batch_size, lr=lr, val_every=val_every,
                   ckpt_every=ckpt_every, workers=workers)
    _check_device(device)
    settings = solver_settings(solver)
    if init is not None and resume is not None:
        raise D3LVOInputError(init, "--init starts a new training; --resume continues one: give one of them")
    if init is not None:
        load_checkpoint(init)  # a bad file is one error before any work
    from models.train_config import model_config

    if preset not in ("default", "small", "paper"):
        raise D3LVOInputError(None, f"the preset (--preset, or preset in the config's [model]) must be one of "
                                    f"default, small, paper, not {preset!r}")
    cfg = model_config(config, {**file["model"], "preset": preset}, mode=mode, completion=completion,
                       pose_head=pose_head, **settings)
    from d3lvo_deploy.sequence import KittiSequence

    for d in [*data, *val]:
        if not d.is_dir():
            raise D3LVOInputError(d, "sequence folder not found")
        # read every sequence's layout and poses now, so a bad folder is one error before the bar
        s = KittiSequence.open(d)
        if s.ground_truth is None:
            raise D3LVOInputError(d, "has no ground-truth poses (poses.txt inside, or poses/NN.txt beside "
                                     "sequences/NN): training and validation need them")
        if len(s) < 2:
            raise D3LVOInputError(d, f"has {len(s)} frame: training and validation need pairs, two frames at least")
    if int(os.environ.get("RANK", "0")) == 0:  # the rank that writes the checkpoints
        _check_out(Path(out))
        continues = resume is not None and Path(out).exists() and os.path.samefile(out, resume)
        if not continues:  # a new training (or one resumed into another file) would overwrite an earlier one
            old = [p for p in (Path(out), best_path(out)) if p.is_file()]
            if old:
                also = f" (--resume {resume} writes into --out, not into itself)" if resume is not None else ""
                raise D3LVOInputError(old[0], f"exists already, from an earlier training: --resume {out} continues it; "
                                              f"a new training needs another --out (or the old files moved away){also}")
    if resume is not None:
        ck = load_checkpoint(resume)
        last = min(steps, stop_at) if stop_at is not None else steps
        if ck["step"] >= last:
            raise D3LVOInputError(resume, f"is at step {ck['step']} already: nothing to train up to "
                                          f"{'--stop-at' if stop_at is not None and stop_at < steps else '--steps'} "
                                          f"{last} (give more steps)")
        # the preset (size, levels) comes from the checkpoint; a different mode or head is refused
        # in train() with the differing fields named
        preset_keys = ("height", "width", "flow_levels", "gn_extra_levels")
        # solver settings carry over from the checkpoint unless --set names them
        carried = preset_keys + tuple(k for k in SOLVER_KEYS if k not in settings)
        if replace(cfg, **{k: getattr(ck["config"], k) for k in carried}) == replace(ck["config"], **settings):
            cfg = replace(ck["config"], **settings)
        else:  # another model than the checkpoint's: one line now, not after the first steps
            asked, trained = replace(cfg, **{k: getattr(ck["config"], k) for k in carried}), replace(ck["config"], **settings)
            differ = sorted(f.name for f in fields(asked) if getattr(asked, f.name) != getattr(trained, f.name))
            raise D3LVOInputError(resume, f"was trained as another model than asked (differs in: {', '.join(differ)}); "
                                          "leave those options out to continue it as it was")
        console.print(f"resumed at step {ck['step']} of {resume}", highlight=False)
    try:
        LossConfig(**file["loss"])
    except ValueError as e:
        raise D3LVOInputError(config, f"[loss] {e}") from None
    tc = TrainConfig(data=[str(d) for d in data], val=[str(v) for v in val], out=str(out), steps=steps, stop_at=stop_at,
                     batch_size=batch_size, lr=lr, val_every=val_every, ckpt_every=ckpt_every, seed=seed,
                     device=device, num_workers=workers, init=str(init) if init else None, precision=precision,
                     depth_cache=str(depth_cache) if depth_cache else None,
                     loss=replace(LossConfig(**file["loss"]), solver_pose_weight=solver_loss),
                     augment=AugmentConfig(**file["augment"]), **file["train"])
    if solver_loss < 0 or (solver_loss > 0 and cfg.pose_head != "points"):
        raise D3LVOInputError(None, "--solver-loss is a non-negative weight for the point head (--pose-head points)")
    if precision == "fp16":
        import torch

        if device == "cpu" or not torch.cuda.is_available():
            raise D3LVOInputError(None, "--precision fp16 trains on a CUDA GPU (its gradient scaler); use bf16 on the CPU")
    rank0 = int(os.environ.get("RANK", "0")) == 0
    if rank0 and resume is None:
        from models.train_config import RECORD_HEADER, write_train_config

        record = Path(out).with_suffix(".toml")  # the resolved configuration, beside the checkpoint
        # a hand-written --config there would be replaced; one a training wrote is rewritten as it repeats
        if (config is not None and record.exists() and os.path.samefile(record, config)
                and not Path(config).read_text(errors="replace").startswith(RECORD_HEADER)):
            raise D3LVOInputError(config, f"is where --out {out} writes its training's resolved configuration: "
                                          "name the checkpoint otherwise (e.g. --out "
                                          f"{Path(out).with_name(Path(out).stem + '_run.pt')})")
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        console.print(f"configuration in {write_train_config(record, cfg, tc)} "
                      "(--config repeats it)", highlight=False)
    with frame_progress() as bar:
        task = bar.add_task("train", total=steps, rate="", visible=rank0)

        def on_step(step: int, rec: dict) -> None:
            bar.update(task, completed=step, rate=f"loss {rec['loss']:.3f}")
            if "val" in rec:
                for name, m in rec["val"].items():
                    t = "n/a" if m["t_rel"] is None else f"{m['t_rel']:.2f} %"
                    console.print(f"step {step} val {name}: t_rel {t}, ATE {m['ate']:.3f} m, "
                                  f"RPE {m['rpe_t']:.3f} m / {m['rpe_r']:.3f} deg", highlight=False)
                    console.print("  " + baseline_line(m), highlight=False)
                if rec.get("best"):
                    console.print(f"  best so far: saved {best_path(out)}", highlight=False)

        try:
            rec = train(cfg, tc, resume=str(resume) if resume else None, on_step=on_step,
                        on_note=lambda note: console.print(note, highlight=False))
        except TrainingInterrupted as e:
            bar.stop()
            if e.step and Path(e.path).is_file():
                console.print(lead("interrupted", "yellow", f" at step {e.step}: saved {e.path}; continue with "
                                                            f"--resume {e.path}"), highlight=False)
            else:
                console.print(lead("interrupted", "yellow", " before the first step: nothing was saved"), highlight=False)
            raise typer.Exit(130) from None
    if rank0:
        if rec.get("step") is None or not Path(out).is_file():
            raise D3LVOInputError(out, "no step was trained, so no checkpoint was written")
        console.print(f"checkpoint {out} at step {rec.get('step')} (loss {rec.get('loss', float('nan')):.4f})",
                      highlight=False)


def _check_numbers(**values) -> None:
    """Counts and rates that cannot train, one error naming the option before any work (a zero
    --ckpt-every would divide by zero at the first step, a negative --lr end in NaN)."""
    import math

    least = {"steps": 1, "stop_at": 1, "batch_size": 1, "val_every": 1, "ckpt_every": 1, "workers": 0}
    for name, v in values.items():
        flag = "--" + name.replace("_", "-")
        if name == "lr":
            if not (math.isfinite(v) and v > 0):
                raise D3LVOInputError(None, f"{flag} must be a positive learning rate, not {v}")
        elif v is not None and v < least[name]:
            raise D3LVOInputError(None, f"{flag} must be at least {least[name]}, not {v}")


def _check_device(device: str) -> None:
    if device not in ("auto", "cpu", "cuda"):
        raise D3LVOInputError(None, f"--device must be auto, cpu or cuda, not {device!r}")
    if device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise D3LVOInputError(None, "--device cuda: this torch sees no CUDA GPU (a CPU build, or no driver); "
                                        "--device cpu trains here")


def _check_out(out: Path) -> None:
    """The checkpoint can be written where it is asked for: found out at the first save, the steps
    before it would be lost."""
    if out.is_dir():
        raise D3LVOInputError(out, "is a folder; --out names the checkpoint file to write (e.g. runs/model.pt)")
    blocker = next((p for p in out.parents if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise D3LVOInputError(out, f"cannot be written: {blocker} is a file, not a folder")
    from d3lvo_deploy.results import make_output_folder

    make_output_folder(out.parent, "--out", "the checkpoint")  # its probe file is per process (torchrun)
