"""The classical tracker with another robust weight, or with frame t's scan as a gate on its points.

    .venv/bin/python scripts/robust_weights.py VARIANT DRIVE...

Runs `d3lvo run DRIVE --method direct` (the bundled model's classical mode, without its scan gate
but for `gate:T`) with its Huber weight replaced, everywhere the tracker uses it (the Gauss-Newton steps and the exposure match), and
prints each drive's t_rel (ATE where the drive is too short for it), then the mean t_rel. The scale
sigma is the tracker's own (1.4826 x the median |r|, re-estimated every third step). VARIANT:

- `huber`: the tracker's own weight (threshold 1.345 sigma), the row the others are read against;
- `tukey`: Tukey's biweight (1 - (r/c)^2)^2, 0 beyond c = 4.685 sigma: a point far off counts nothing;
- `cauchy`: 1 / (1 + (r/c)^2), c = 2.385 sigma;
- `t`: Student-t with 5 degrees of freedom, its scale iterated to a fixed point on the residuals
  (Kerl, Sturm, Cremers, "Robust odometry estimation for RGB-D cameras", ICRA 2013, chosen there
  over Huber and Tukey for scenes with moving people);
- `scangate:TAU`: Huber, then the points whose depth in frame t under that motion differs from
  frame t's own LiDAR return at their pixel by more than TAU (relative) are dropped, and the pair
  is solved again from the same start without them: a gate on what moves that reads no image;
- `gate:TAU`: the same gate under the starting motion instead, before the one solve
  (`DirectConfig.scan_gate`, the model setting `pt_scan_gate`).

docs/evaluation.md ("Frame t's scan as a gate before the solve") quotes it.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from d3lvo_deploy import direct
from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.direct import DirectConfig, DirectOdometry, TrackedFrame, scan_gated
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.evaluation import evaluate
from d3lvo_deploy.manifest import load_manifest
from d3lvo_deploy.sequence import KittiSequence

TUKEY_C, CAUCHY_C, T_DOF = 4.685, 2.385, 5.0  # 95 % efficiency on Gaussian residuals; Kerl et al.'s nu


def sigma_of(k: float) -> float:
    """The tracker's robust sigma from its Huber threshold k = 1.345 sigma."""
    return k / direct.HUBER_K


def tukey(r: np.ndarray, k: float) -> np.ndarray:
    c = TUKEY_C * sigma_of(k)
    return np.where(np.abs(r) < c, (1.0 - (r / c) ** 2) ** 2, 0.0)


def cauchy(r: np.ndarray, k: float) -> np.ndarray:
    return 1.0 / (1.0 + (r / (CAUCHY_C * sigma_of(k))) ** 2)


def student_t(r: np.ndarray, k: float) -> np.ndarray:
    s2 = sigma_of(k) ** 2
    for _ in range(5):  # the scale's fixed point, from the robust sigma
        s2 = max(float(np.mean(r * r * (T_DOF + 1.0) / (T_DOF + r * r / s2))), 1e-12)
    return (T_DOF + 1.0) / (T_DOF + r * r / s2)


WEIGHTS = {"tukey": tukey, "cauchy": cauchy, "t": student_t}


def run(variant: str, drive: Path) -> float | None:
    seq = KittiSequence.open(drive)
    if seq.ground_truth is None:
        raise D3LVOInputError(drive, "has no poses.txt")
    # the bundled model's classical mode without its scan gate, which only `gate:T` sets
    cfg = replace(DirectConfig.of_model(load_manifest(bundled_model_dir())["model_config"]),
                  scan_gate=float(variant.split(":")[1]) if variant.startswith("gate:") else 0.0)
    odo = DirectOdometry(seq.calib, cfg)
    shipped_weights, shipped_track, dropped = direct.huber_weights, direct.track, []
    if variant in WEIGHTS:
        w = WEIGHTS[variant]
        direct.huber_weights = lambda r, k=None: w(r, direct.huber_threshold(r) if k is None else k)
    elif variant.startswith("scangate:"):
        if not cfg.reads_scan:
            raise D3LVOInputError(None, "scangate needs a model whose classical mode keeps frame t's scan")
        tau = float(variant.split(":")[1])

        def gated(prev: TrackedFrame, cur: TrackedFrame, start: np.ndarray, c: DirectConfig) -> np.ndarray:
            A = shipped_track(prev, cur, start, c)
            kept = scan_gated(prev, cur.depth, A, tau)  # the shipped gate, at the solved motion
            dropped.append(1.0 - len(kept.points) / len(prev.points) if len(prev.points) else 0.0)
            if kept is prev or len(kept.points) < 12:
                return A
            return shipped_track(kept, cur, start, c)

        direct.track = gated
    try:
        poses = np.stack([odo.step(seq.image(i), seq.scan(i), float(seq.times[i])) for i in range(len(seq))])
    finally:
        direct.huber_weights, direct.track = shipped_weights, shipped_track
    e = evaluate(seq.ground_truth.poses, poses)
    score = f"t_rel {e.t_rel:.4f} %" if e.t_rel is not None else f"ATE {e.ate:.4f} m"
    gate = f", {100 * np.mean(dropped):.1f} % of the points dropped per pair" if dropped else ""
    print(f"{drive.name}: {variant}: {score}{gate}", flush=True)
    return e.t_rel


if __name__ == "__main__":
    args = sys.argv[1:]
    variant = args[0] if args else ""
    ok = variant == "huber" or variant in WEIGHTS
    if variant.startswith(("scangate:", "gate:")):
        try:
            ok = float(variant.split(":")[1]) > 0
        except ValueError:
            ok = False
    if not ok or len(args) < 2:
        sys.exit(__doc__)
    try:
        scores = [t for t in (run(variant, Path(d)) for d in args[1:]) if t is not None]
    except D3LVOInputError as e:
        sys.exit(f"error: {e}")
    if scores:
        print(f"{variant}: mean t_rel {np.mean(scores):.4f} % over {len(scores)} drives")
