"""manifest.json of an exported model folder, and its verification before anything is run.

The runtime refuses a folder whose files do not match the manifest (hash, input/output names,
shapes): a tampered or mixed-up model would otherwise produce a plausible but wrong trajectory.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from .config_values import describe, fits
from .errors import D3LVOInputError

MANIFEST_FORMAT = "d3lvo-onnx"
# 2: stages take normalised RGB and inverse depth (1 took RGB in [0, 1] and metres)
MANIFEST_VERSION = 2
STANDARD_DOMAINS = ("", "ai.onnx")
STAGES = ("completion", "encoder", "flowpose")  # and, for the point solver, "classical" and "flowpose_weighted"
# a stage may also carry a graph of the same inputs and outputs for one engine, under that engine's
# name: the flow+pose stage's `onnxruntime` graph takes its bilinear samples as Gathers (models/sampling.py)
ENGINE_GRAPHS = ("onnxruntime",)
# the `model_config` entries the runtime reads, each with a value of its kind (`config_values.fits`):
# a hand-edited or truncated manifest is one error naming the entry when the folder is opened,
# not a traceback at the first frame; the point solver's only in a point-solver model's, the
# optional ones only where present (older exports lack them, and the runtime takes their defaults)
RUNTIME_CONFIG = {"height": 1, "width": 1, "min_depth": 1.0, "max_depth": 1.0, "rgb_mean": [1.0], "rgb_std": [1.0]}
POINT_SOLVER_CONFIG = {"pt_iters": [1], "pt_stop": 1.0, "pt_damping": 1.0, "pt_min_gradient": 1.0, "pt_capacity": 1}
OPTIONAL_CONFIG = {"pt_scale_every": 1, "pt_median_stride": 1, "pt_refine": 0, "pt_affine": False,
                   "pt_fine_restart": 0.0, "pt_restart_depth": 0.0, "pt_scan_gate": 0.0, "pt_select_hold": 0}


def for_engine(st: dict, backend: str) -> dict:
    """The manifest entry of a stage as `backend` opens it: its own graph's file and sha256 where
    the export wrote one for that engine."""
    own = st.get(backend) if backend in ENGINE_GRAPHS else None
    return {**st, "file": own["file"], "sha256": own["sha256"]} if isinstance(own, dict) else st


def _names_a_file(entry) -> bool:
    """A stage's (or an engine graph's) entry names its file and that file's sha256."""
    return isinstance(entry, dict) and isinstance(entry.get("file"), str) and isinstance(entry.get("sha256"), str)


def graph_files(m: dict) -> list[str]:
    """Every graph file a (loaded) manifest lists: each stage's own, then its engines' graphs."""
    return [e["file"] for st in m["stages"].values() for e in (st, *(st[k] for k in ENGINE_GRAPHS if k in st))]


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def load_manifest(model_dir: str | Path, verify_hashes: bool = True) -> dict:
    model_dir = Path(model_dir)
    path = model_dir / "manifest.json"
    if model_dir.is_file():
        if model_dir.suffix in (".pt", ".pth"):
            raise D3LVOInputError(model_dir, "is a PyTorch checkpoint; the runtime reads an exported folder: "
                                             f"d3lvo export --ckpt {model_dir} --out DIR, then pass DIR")
        if model_dir.suffix == ".onnx":
            raise D3LVOInputError(model_dir, "is one ONNX file; pass the folder written by `d3lvo export` "
                                             "(its manifest.json lists the stages)")
        raise D3LVOInputError(model_dir, "is a file; pass the folder written by `d3lvo export`")
    if not model_dir.exists():
        raise D3LVOInputError(model_dir, "model folder not found")
    if not path.is_file():
        raise D3LVOInputError(model_dir, "no manifest.json: not a folder written by `d3lvo export`")
    try:
        m = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise D3LVOInputError(path, f"not valid JSON ({e.msg}, line {e.lineno})") from None
    if not isinstance(m, dict) or m.get("format") != MANIFEST_FORMAT:
        raise D3LVOInputError(path, f"not a D3LVO manifest (format must be {MANIFEST_FORMAT!r})")
    if m.get("version") != MANIFEST_VERSION:
        raise D3LVOInputError(path, f"manifest version {m.get('version')}, this runtime reads {MANIFEST_VERSION}: "
                                    "re-export the checkpoint with `d3lvo export`")
    missing = [k for k in ("model_config", "depth_input", "input", "opset") if k not in m]
    if missing:  # what the runtime and the reduced-precision conversion read
        raise D3LVOInputError(path, f"has no {missing[0]!r}: re-export the checkpoint with `d3lvo export`")
    check_model_config(m, path)
    stages = m.get("stages", {})
    for name in ("encoder", "flowpose"):
        if name not in stages:
            raise D3LVOInputError(path, f"lists no {name} stage")
    for name, st in stages.items():
        if not _names_a_file(st):
            raise D3LVOInputError(path, f"stage {name!r} has no file name or no sha256: re-export with `d3lvo export`")
        entries = [(name, st)]
        for engine in ENGINE_GRAPHS:
            own = st.get(engine)
            if own is None:
                continue
            if not _names_a_file(own):
                raise D3LVOInputError(path, f"stage {name!r}: its {engine} graph has no file name or no sha256")
            entries.append((f"{name} ({engine})", own))
        for label, entry in entries:
            f = model_dir / entry["file"]
            if not f.is_file():
                raise D3LVOInputError(f, f"{label} model listed in the manifest is missing")
            if verify_hashes and sha256_file(f) != entry["sha256"]:
                raise D3LVOInputError(f, "sha256 differs from manifest.json (modified or from another export)")
    return m


def check_model_config(m: dict, path: Path) -> None:
    """The input size and the `model_config` entries the runtime reads, each of its kind; the size
    the same in both and in the encoder's graph inputs."""
    size = m["input"]
    if not (isinstance(size, dict) and all(fits(size.get(k), 1) and size[k] > 0 for k in ("height", "width"))):
        raise D3LVOInputError(path, "'input' must give the network's height and width as whole numbers above 0: "
                                    "re-export the checkpoint with `d3lvo export`")
    cfg = m["model_config"]
    if not isinstance(cfg, dict):
        raise D3LVOInputError(path, "'model_config' must be the exported model's settings (a JSON object)")
    wanted = dict(RUNTIME_CONFIG, **(POINT_SOLVER_CONFIG if cfg.get("pose_head") == "points" else {}))
    for key, like in {**wanted, **{k: v for k, v in OPTIONAL_CONFIG.items() if k in cfg}}.items():
        if key not in cfg:
            raise D3LVOInputError(path, f"model_config has no {key!r}: re-export the checkpoint with `d3lvo export`")
        per_channel = key.startswith("rgb")  # a value per colour channel; the solver's iterations: one per level
        ok = fits(cfg[key], like)
        if ok and isinstance(like, list):
            ok = len(cfg[key]) == 3 if per_channel else len(cfg[key]) > 0
        if not ok:
            kind = (f"a list of {'three ' if per_channel else ''}{describe(like)}" if isinstance(like, list)
                    else describe(like))
            raise D3LVOInputError(path, f"model_config {key!r} is {cfg[key]!r}, it must be {kind}: re-export the "
                                        "checkpoint with `d3lvo export`")
    for key in ("height", "width"):
        if cfg[key] != size[key]:
            raise D3LVOInputError(path, f"model_config {key!r} is {cfg[key]}, its 'input' {key} {size[key]}: "
                                        "the manifest was edited or mixed from two exports")
    rgb = next((i for i in m.get("stages", {}).get("encoder", {}).get("inputs", []) if i.get("name") == "rgb_norm"), None)
    shape = list(rgb.get("shape", [])[2:]) if rgb is not None else []
    if all(isinstance(d, int) for d in shape) and len(shape) == 2 and shape != [size["height"], size["width"]]:
        raise D3LVOInputError(path, f"'input' is {size['width']}x{size['height']}, the encoder's graph takes "
                                    f"{shape[1]}x{shape[0]}: the manifest was edited or mixed from "
                                    "two exports")
