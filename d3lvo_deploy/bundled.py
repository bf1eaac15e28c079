"""The default model shipped inside the package (trained by `scripts/train_default.sh`)."""

from __future__ import annotations

from pathlib import Path

from .errors import D3LVOInputError

BUNDLED = Path(__file__).resolve().parent / "default_model"


def bundled_model_dir() -> Path:
    if not (BUNDLED / "manifest.json").is_file():
        raise D3LVOInputError(BUNDLED, "no bundled default model in this install; pass --onnx DIR")
    return BUNDLED
