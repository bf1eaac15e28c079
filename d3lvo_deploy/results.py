"""A run's results folder: everything needed to read, compare and reproduce one run, together.

    results/<name>_<YYYYmmdd-HHMMSS>/   (`latest` beside it points at the newest)
        poses.txt        KITTI format, one line per frame, written as frames finish
        poses_tum.txt    the same poses with the frames' times (TUM)
        config.toml      every option of the run, the model's hash, the engine, the CPU
        metrics.json     scores against ground truth, when the recording has it
        latency.json     per-stage mean / p90 / max and every frame's total, in ms
        trajectory.png   when matplotlib is installed
    and the --viz folder / --rerun recording when asked for.

`d3lvo run --config results/.../config.toml` reads the [run] table back: the same options,
hence the same poses.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import D3LVOInputError
from .poses import read_poses, write_poses

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the same parser, as a package
    import tomli as tomllib

POSES, POSES_TUM, CONFIG, METRICS, LATENCY, PLOT = (
    "poses.txt", "poses_tum.txt", "config.toml", "metrics.json", "latency.json", "trajectory.png")


def default_folder(base: Path, name: str, now: float | None = None) -> Path:
    """`base/<name>_<time>`, created here so that two runs started in the same second (say, one
    per engine) never share one: the second gets `-2`."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
    try:
        base.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise D3LVOInputError(base, f"cannot create the results folder ({e.strerror})") from None
    for k in range(1, 1000):
        folder = base / (f"{name}_{stamp}" if k == 1 else f"{name}_{stamp}-{k}")
        try:
            folder.mkdir()
            return folder
        except FileExistsError:
            continue
    raise D3LVOInputError(base, f"a thousand runs of {name} started at {stamp}: no free folder name")


def make_output_folder(path: Path, option: str, holds: str) -> Path:
    """`path` as a folder that can be written (made where missing), or one error naming `option`:
    found out at the first write, the work before it would be lost."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise D3LVOInputError(path, f"is a file; {option} names the folder for {holds}")
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".write_test{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise D3LVOInputError(path, f"cannot write the folder for {holds} ({e.strerror})") from None
    return path


def remove_if_empty(folder: Path) -> None:
    """A run that stopped at its checks leaves no empty results folder behind."""
    try:
        folder.rmdir()
    except OSError:
        pass


def link_latest(folder: Path) -> bool:
    """`latest` beside the folder, a relative link, replaced atomically; False (and nothing
    touched) where `latest` is a real folder or file of the user's, or links cannot be made."""
    link = folder.parent / "latest"
    if link.exists() and not link.is_symlink():
        return False
    tmp = folder.parent / f".latest-{os.getpid()}"
    try:
        if tmp.is_symlink():
            tmp.unlink()
        tmp.symlink_to(folder.name)
        os.replace(tmp, link)
    except OSError:  # a file system without links: the folder itself is what matters
        if tmp.is_symlink():
            tmp.unlink()
        return False
    return True


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v)) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return json.dumps(str(v))  # a JSON string is a valid TOML basic string


def to_toml(tables: dict[str, dict]) -> str:
    """Flat tables of scalars and lists (None left out: TOML has no null)."""
    lines = []
    for name, table in tables.items():
        lines.append(f"[{name}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in table.items() if v is not None]
        lines.append("")
    return "\n".join(lines)


def read_toml(path: str | Path, what: str = "config file") -> dict:
    """A TOML file as a dict; a missing or malformed file is one error naming it."""
    path = Path(path)
    if not path.is_file():
        raise D3LVOInputError(path, f"{what} not found")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise D3LVOInputError(path, f"is not valid TOML ({e})") from None
    except UnicodeDecodeError as e:  # TOML is UTF-8 (a comment saved as Latin-1, say)
        raise D3LVOInputError(path, f"is not UTF-8 text, as TOML must be (byte {e.start})") from None


def read_config(path: str | Path) -> dict:
    """The [run] table of a results folder's config.toml (or of a file written by hand)."""
    path = Path(path)
    if path.is_dir():
        path = path / CONFIG
    data = read_toml(path)
    run = data.get("run")
    if not isinstance(run, dict):
        raise D3LVOInputError(path, "has no [run] table (d3lvo run writes one into each results folder)")
    return run


# the [run] options that decide which frame each pose belongs to and how it was estimated: a
# resumed run appends to the poses of an earlier one only where it agrees on each (the end may
# grow; threads and engine change no pose beyond rounding)
RESUME_KEYS = ("path", "fmt", "calib", "image_topic", "cloud_topic", "info_topic", "max_dt", "method", "start",
               "max_accel")
# what a run record without the key ran with (a setting newer than the record)
RESUME_DEFAULTS = {"max_accel": 0.0}


def record_file(out: str | Path) -> Path:
    """Beside a trajectory written with `d3lvo run --out`: its run's config (the [run] and [model]
    tables of a results folder's config.toml), which --resume checks and --config repeats."""
    out = Path(out)
    return out.with_name(out.name + ".config.toml")


def check_resume(record: Path, current: dict[str, dict], poses: Path) -> None:
    """--resume would append this run's poses (`current`: its [run] and [model] tables as written)
    to those in `poses` of the run `record` holds: one error naming what differs, before any pose is added,
    rather than one file holding two recordings' frames."""
    old = read_toml(record, "run record")
    if not isinstance(old.get("run"), dict) or not isinstance(old.get("model", {}), dict):
        raise D3LVOInputError(record, "has no [run] table, or a [model] that is no table (d3lvo run writes both)")
    pairs = [(f"{k}", old["run"].get(k, RESUME_DEFAULTS.get(k)), current["run"].get(k)) for k in RESUME_KEYS]
    pairs.append(("model", old.get("model", {}).get("manifest_sha256"), current["model"].get("manifest_sha256")))
    for key, was, now in pairs:
        was, now = (None if v is None else str(v) if isinstance(v, Path) else v for v in (was, now))
        if was != now:
            what = "model (manifest sha256)" if key == "model" else key
            raise D3LVOInputError(record, f"the poses in {poses} are of a run with {what} = {_shown(was, key)}, this one "
                                          f"has {_shown(now, key)}: --resume continues the same run only (write this one "
                                          "elsewhere, or --overwrite to start over)")


def _shown(v, key: str) -> str:
    return "none" if v is None else f"{v[:12]}..." if key == "model" else repr(v)


@dataclass
class ResultsFolder:
    path: Path

    @property
    def poses(self) -> Path:
        return self.path / POSES

    def create(self) -> "ResultsFolder":
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise D3LVOInputError(self.path, f"cannot create the results folder ({e.strerror})") from None
        return self

    def write_text(self, name: str, text: str) -> Path:
        p = self.path / name
        tmp = p.with_name(p.name + ".tmp")
        tmp.write_text(text)
        os.replace(tmp, p)
        return p

    def write_json(self, name: str, data: dict) -> Path:
        return self.write_text(name, json.dumps(data, indent=2, default=_jsonable) + "\n")

    def write_tum(self, times: np.ndarray, start: int) -> Path:
        """poses.txt again with each frame's time: TUM, for tools that want stamps (evo, rpg)."""
        traj = read_poses(self.poses, "kitti")
        p = self.path / POSES_TUM
        write_poses(p, traj.poses, "tum", np.asarray(times)[start:start + len(traj)])
        return p


def _jsonable(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(type(v).__name__)


def latency_report(summary) -> dict:
    """A run's `RunSummary` as latency.json: per-stage statistics, every frame's total, and the
    throughput beside them (they differ with the pipeline)."""
    total = summary.latencies_ms.get("total", [])
    return {"unit": "ms", "stages": summary.stats(), "frames": len(total),
            "median_total": float(np.median(total)) if total else None, "per_frame_total": total,
            "throughput_fps": summary.throughput, "wall_s": summary.wall_s, "pipelined": summary.pipelined}
