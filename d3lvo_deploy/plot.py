"""Top-view (x-z) trajectory plots; Agg backend so it works on headless vehicles and CI."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import D3LVOInputError

def plot_path(path: Path) -> Path:
    """Where `--plot PATH` writes: PATH.png without a suffix (and said so), else any kind matplotlib
    writes, or one error naming the path before any work."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    path = Path(path)
    if not path.name:  # "" or a path ending in a folder: nothing to name the picture after
        raise D3LVOInputError(None, "--plot names no file: give the picture's path, e.g. traj.png")
    if not path.suffix:
        return path.with_name(path.name + ".png")
    kinds = sorted(FigureCanvasAgg.get_supported_filetypes())
    if path.suffix.lower().lstrip(".") not in kinds:
        raise D3LVOInputError(path, f"--plot writes {', '.join('.' + k for k in kinds)}; not {path.suffix}")
    return path


def plot_trajectories(out: str | Path, trajectories: dict[str, np.ndarray], title: str = "") -> Path:
    """Draw each (N,4,4) trajectory in cam0's x-z plane (KITTI's bird's-eye view) and save a PNG."""
    from .extras import require

    require("matplotlib", what="a trajectory plot")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    fig, ax = plt.subplots(figsize=(6, 6), dpi=110)
    for label, poses in trajectories.items():
        p = np.asarray(poses)[:, :3, 3]
        ax.plot(p[:, 0], p[:, 2], label=label, lw=1.5, ls="--" if label.lower().startswith("gt") else "-")
    first = np.asarray(next(iter(trajectories.values())))[0, :3, 3]
    ax.plot(first[0], first[2], "ko", ms=4, label="start")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("z [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out
