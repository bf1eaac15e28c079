"""Checkpoints that say what they are: a format tag and version, the model config, training state."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import torch

from d3lvo_deploy.errors import D3LVOInputError

from .config import D3LVOConfig

FORMAT = "d3lvo-checkpoint"
VERSION = 1


def save_checkpoint(path: str | Path, model, cfg: D3LVOConfig, **state) -> None:
    """Atomic: written to a temporary file and renamed, so a killed run keeps the last good one."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        torch.save({"format": FORMAT, "version": VERSION, "config": cfg.to_dict(), "model": model.state_dict(), **state}, tmp)
        os.replace(tmp, path)
    except OSError as e:
        raise D3LVOInputError(path, f"cannot write the checkpoint ({e.strerror})") from None


def load_checkpoint(path: str | Path, expect: D3LVOConfig | None = None, ignore: tuple[str, ...] = ()) -> dict:
    """Read and validate; with `expect`, refuse a checkpoint made with another config (except in
    the `ignore` fields, e.g. solver settings that have no weights)."""
    path = Path(path)
    if path.is_dir():
        hint = (" (an exported ONNX folder; --ckpt takes the .pt checkpoint it was exported from)"
                if (path / "manifest.json").is_file() else "")
        raise D3LVOInputError(path, f"is a folder, not a checkpoint file{hint}")
    if not path.is_file():
        raise D3LVOInputError(path, "checkpoint not found")
    try:
        ck = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # torch raises many types for a non-checkpoint file
        raise D3LVOInputError(path, f"not a PyTorch checkpoint ({type(e).__name__})") from None
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise D3LVOInputError(path, "not a D3LVO checkpoint (no 'd3lvo-checkpoint' format tag)")
    if ck.get("version") != VERSION:
        raise D3LVOInputError(path, f"checkpoint format version {ck.get('version')}, this toolkit reads {VERSION}")
    for key, kind, what in (("config", dict, "a model config"), ("model", dict, "the weights (a state dict)")):
        if not isinstance(ck.get(key), kind):
            raise D3LVOInputError(path, f"'{key}' is missing or not {what}: not a checkpoint `d3lvo train` wrote")
    try:
        cfg = D3LVOConfig.from_dict(ck["config"])
    except (TypeError, ValueError) as e:
        raise D3LVOInputError(path, f"invalid model config in checkpoint ({e})") from None
    if expect is not None and replace(cfg, **{k: getattr(expect, k) for k in ignore}) != expect:
        diff = sorted(k for k, v in expect.to_dict().items() if getattr(cfg, k) != v and k not in ignore)
        raise D3LVOInputError(path, f"checkpoint was made with another model config (differs in: {', '.join(diff)})")
    ck["config"] = cfg
    ck["path"] = str(path)
    return ck


def build_model(ck: dict):
    """A D3LVO model with the checkpoint's weights, in eval mode."""
    from .d3lvo import D3LVO

    model = D3LVO(ck["config"])
    try:
        model.load_state_dict(ck["model"])
    except RuntimeError as e:
        first = str(e).splitlines()[1].strip() if len(str(e).splitlines()) > 1 else str(e)
        raise D3LVOInputError(ck.get("path"), f"weights do not fit the model config ({first[:200]})") from None
    return model.eval()


def slim_checkpoint(src: str | Path, dst: str | Path, solver: dict | None = None) -> Path:
    """Weights, config and training record only (no optimizer state): what ships in the package.
    `solver`: solver settings without weights to store instead of the training's (SOLVER_KEYS)."""
    from .config import check_solver_settings

    ck = load_checkpoint(src)
    keep = {k: ck[k] for k in ("step", "history", "train_config", "loss") if k in ck}
    model = build_model(ck)
    check_solver_settings(solver or {})
    save_checkpoint(dst, model, replace(ck["config"], **(solver or {})), **keep)
    return Path(dst)
