"""The default model shipped inside the package (trained by `scripts/train_default.sh`), and the
real KITTI frames the project keeps beside the checkout (../shared/data), when present."""

from __future__ import annotations

from pathlib import Path

from .errors import D3LVOInputError

BUNDLED = Path(__file__).resolve().parent / "default_model"


def bundled_model_dir() -> Path:
    if not (BUNDLED / "manifest.json").is_file():
        raise D3LVOInputError(BUNDLED, "no bundled default model in this install; pass --onnx DIR")
    return BUNDLED


def find_real_frames() -> Path | None:
    """The 20 real KITTI frames in ../shared/data, looked for beside the repo and the working dir."""
    rel = Path("shared") / "data" / "kitti_raw_snippet" / "sequences" / "r0926"
    for base in (Path(__file__).resolve().parents[2], Path.cwd().parent, Path.cwd()):
        if (base / rel).is_dir():
            return base / rel
    return None
