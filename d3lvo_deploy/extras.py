"""Optional parts of the install: a command that needs a missing extra says which, in one line.

A vehicle installs `d3lvo-deploy` alone (numpy, onnxruntime, opencv, typer, rich): `run`, `eval`
and the `Odometry` API. Training, export and parity need `[train]` (torch, onnx), the synthetic
world `[synth]` (embreex), plots `[plot]` (matplotlib), the Ray engine `[ray]`, ROS bags and
PCD/PLY scans `[sensors]` (rosbags, pypcd4, plyfile).
"""

from __future__ import annotations

import importlib

from .errors import D3LVOInputError

EXTRAS = {"torch": "train", "onnx": "train", "embreex": "synth", "matplotlib": "plot", "ray": "ray",
          "openvino": "openvino", "rerun": "rerun", "rosbags": "sensors", "rosbags.image": "sensors",
          "pypcd4": "sensors", "plyfile": "sensors"}


def installed(module: str) -> bool:
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


def require(*modules: str, what: str) -> None:
    """Import-check `modules`; if one is missing, raise the one-line error naming its extra."""
    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError:
            extra = EXTRAS.get(name, "all")
            raise D3LVOInputError(None, f"{what} needs {name}, which this install lacks: "
                                        f"pip install 'd3lvo-deploy[{extra}]'") from None
