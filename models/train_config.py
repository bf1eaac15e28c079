"""`d3lvo train --config FILE.toml`: every model, schedule, loss and augmentation option in one
file, checked key by key; and the resolved file written beside each checkpoint, so that a run
is repeated with `--config runs/x.toml`.

    [model]            # preset (default | small | paper), then any D3LVOConfig field
    preset = "paper"
    flow_levels = [3, 2, 1, 0]
    [train]            # TrainConfig: data, val, out, steps, batch_size, lr, precision, ...
    data = ["kitti/sequences/00", "kitti/sequences/01"]
    [loss]             # LossConfig: alphas, alpha_final, motion_weight, solver_pose_weight, ...
    [augment]          # AugmentConfig: flip, brightness, rotation_deg, cold_start, ...
"""

from __future__ import annotations

import math
import typing
from dataclasses import MISSING, asdict, fields
from pathlib import Path

from d3lvo_deploy.config_values import converted, describe, fits
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.results import read_toml, to_toml

from .config import D3LVOConfig
from .data import AugmentConfig
from .loss import LossConfig

TABLES = ("model", "train", "loss", "augment")


def _defaults(cls) -> dict:
    """Each field's default, or where that is None the type its hint allows besides None (so that
    a file's `stop_at = "one"` is refused as a whole number is wanted, not met at the first step)."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in fields(cls):
        if f.default is not MISSING:
            out[f.name] = f.default
        elif f.default_factory is not MISSING:  # type: ignore[misc]
            out[f.name] = f.default_factory()  # type: ignore[misc]
        else:
            continue
        if out[f.name] is None:
            kinds = [t for t in typing.get_args(hints[f.name]) if t is not type(None)]
            out[f.name] = kinds[0] if len(kinds) == 1 and isinstance(kinds[0], type) else None
    return out


def _check_type(path: Path, table: str, key: str, value, default) -> object:
    """A value of the default's kind (`config_values.fits`), else one error naming the key."""
    if default is None or value is None:
        return value
    if not fits(value, default):
        if isinstance(default, (tuple, list)):
            example = list(default) or ["a", "b"]
            raise D3LVOInputError(path, f"[{table}] {key} = {value!r} should be a list of {describe(default)}, "
                                        f"like {example!r}")
        like = "" if isinstance(default, type) else f", like {default!r}"
        raise D3LVOInputError(path, f"[{table}] {key} = {value!r} should be {describe(default)}{like}")
    return converted(value, default)


# values of the right kind that still cannot train, as (lowest, highest, whether the lowest is allowed),
# and never NaN: a negative grad_clip turns the gradient round (clip_grad_norm_ scales by a negative
# factor) and trains uphill, a negative loss weight rewards that loss, a probability above 1 is 1
BOUNDS = {("train", "lr"): (0.0, None, False), ("train", "balance_lr"): (0.0, None, True),
          ("train", "grad_clip"): (0.0, None, False), ("train", "weight_decay"): (0.0, None, True),
          ("train", "warmup"): (0, None, True),
          ("augment", "flip"): (0.0, 1.0, True), ("augment", "cold_start"): (0.0, 1.0, True),
          ("augment", "held_out_returns"): (0.0, 1.0, True), ("augment", "brightness"): (0.0, 1.0, True),
          ("augment", "rotation_deg"): (0.0, None, True), ("loss", "alpha_final"): (0.0, None, True),
          ("loss", "alphas"): (0.0, None, True)}


def _check_bounds(path: Path, table: str, key: str, value) -> None:
    """A value inside its `BOUNDS` (loss weights: 0 or more), else one error naming the key."""
    low, high, closed = BOUNDS.get((table, key), (0.0, None, True) if key.endswith("_weight") else (None, None, True))
    if low is None or value is None:
        return
    for v in value if isinstance(value, (tuple, list)) else [value]:
        if not math.isfinite(v) or (v < low if closed else v <= low) or (high is not None and v > high):
            span = f"from {low:g} to {high:g}" if high is not None else f"{'at least' if closed else 'above'} {low:g}"
            given = f"{list(value)}: each value" if isinstance(value, (tuple, list)) else f"{value!r}"
            raise D3LVOInputError(path, f"[{table}] {key} = {given} must be {span}")


def read_train_config(path: str | Path) -> dict[str, dict]:
    """{table: {key: value}} with every key known and of the right kind; [model] values are also
    checked by building the model config."""
    from .train import TrainConfig

    path = Path(path)
    data = read_toml(path, "training config")
    unknown = sorted(set(data) - set(TABLES))
    if unknown:
        raise D3LVOInputError(path, f"unknown table [{unknown[0]}] (tables: {', '.join(TABLES)})")
    kinds = {"model": {"preset": "default", **_defaults(D3LVOConfig)},
             "train": {k: v for k, v in _defaults(TrainConfig).items() if k not in ("augment", "loss")}
             | {"data": [], "out": ""},
             "loss": _defaults(LossConfig), "augment": _defaults(AugmentConfig)}
    out: dict[str, dict] = {}
    for table in TABLES:
        values = data.get(table, {})
        if not isinstance(values, dict):
            raise D3LVOInputError(path, f"[{table}] must be a table")
        for key, value in values.items():
            if key not in kinds[table]:
                raise D3LVOInputError(path, f"[{table}] unknown key {key!r}")
            values[key] = _check_type(path, table, key, value, kinds[table][key])
            _check_bounds(path, table, key, values[key])
        out[table] = dict(values)
    model_config(path, out["model"])  # bad values: one error now, not at the first step
    return out


def model_config(path: Path | None, table: dict, **cli) -> D3LVOConfig:
    """The [model] table (preset + fields), with `cli` values on top."""
    values = {**table, **cli}
    preset = values.pop("preset", "default")
    try:
        return D3LVOConfig.preset(preset, **values)
    except (TypeError, ValueError) as e:
        raise D3LVOInputError(path, f"[model] {e}") from None


# the first line of every configuration a training writes (`write_train_config`)
RECORD_HEADER = "# d3lvo train --config THIS_FILE repeats this training (--resume to continue it)\n"


def write_train_config(path: Path, cfg: D3LVOConfig, tc) -> Path:
    """The resolved configuration of a training run, in the file format `--config` reads."""
    train = {k: v for k, v in asdict(tc).items() if k not in ("augment", "loss")}
    # absolute paths: `--config THIS_FILE` repeats the run from any folder (a hand-written file's
    # relative paths are taken from the folder train runs in)
    absolute = lambda p: str(Path(p).resolve())  # noqa: E731
    for key in ("data", "val"):
        train[key] = [absolute(p) for p in train[key]]
    for key in ("out", "init", "depth_cache"):
        if train.get(key):
            train[key] = absolute(train[key])
    text = to_toml({"model": cfg.to_dict(), "train": train, "loss": asdict(tc.loss), "augment": asdict(tc.augment)})
    path.write_text(RECORD_HEADER + text)
    return path
