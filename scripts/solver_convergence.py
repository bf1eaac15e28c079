"""How the classical tracker's Gauss-Newton steps converge, and a Newton step on the Huber cost beside them.

    .venv/bin/python scripts/solver_convergence.py DRIVE [--newton] [--iters 15,15,15] [--out OUT.txt]

Runs `d3lvo run DRIVE --method direct` (the bundled model's classical mode) with each level's
steps recorded, and prints per pyramid level: how many steps the solves took, the median step
(largest component of xi, m and rad) at steps 1, 3, 6, 9, 12 and 15, and the median cosine between
consecutive steps. Steps that keep their direction (cosine near 1) while shrinking slowly creep
towards the minimum: each covers a fraction of the way left. The tracker re-weights the points
(IRLS), and IRLS gives every point beyond the Huber threshold the curvature k/|r|, where the
Huber cost has none, so it over-estimates the curvature and shortens the steps.

`--newton` takes the Hessian from the points within the threshold only (the Huber cost's own
second derivative) and the gradient as before: the same minimum, reached in fewer steps.
`--iters` sets the steps per level (coarse to fine). `--out` writes the poses, to score with
`d3lvo eval --gt DRIVE/poses.txt --est OUT.txt` (docs/performance.md). Without either option the
recorded copy of the step must give the tracker's own poses, and the script checks that it does.
"""

from __future__ import annotations

import argparse
import collections
from dataclasses import replace
from pathlib import Path

import numpy as np

from d3lvo_deploy import direct
from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.datasets import open_sequence
from d3lvo_deploy.direct import DirectConfig, DirectOdometry
from d3lvo_deploy.geometry import axis_angle_to_rot
from d3lvo_deploy.manifest import load_manifest
from d3lvo_deploy.poses import write_poses

AT = (1, 3, 6, 9, 12, 15)


def recording_align_level(steps: dict, newton: bool):
    """`direct.align_level` with each step's xi appended to steps[level width] (one list per
    solve); with `newton`, the Hessian from the points within the Huber threshold only."""

    def align_level(M, X, ref, lvl, iterations, cfg):
        h, w = lvl.shape
        fx, fy = lvl.K[0, 0], lvl.K[1, 1]
        taken = []
        steps[w].append(taken)
        for i in range(iterations):
            Xt = X @ M[:3, :3].T + M[:3, 3]
            front = Xt[:, 2] > 0.1
            uv, zi = direct.project(np.where(front[:, None], Xt, 1.0), lvl.K)
            ok = front & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
            if ok.sum() < 12:
                break
            Xt, uv, zi = Xt[ok], uv[ok], zi[ok]
            s = direct.sample(lvl.stack, uv)
            cur = s[:, 0]
            r = cur - (direct.affine_fit(ref[ok], cur, np.ones_like(cur)) if cfg.affine_brightness else ref[ok])
            if i % cfg.scale_every == 0:
                k = direct.stride_threshold(r, np.flatnonzero(ok), cfg.median_stride)
            if cfg.affine_brightness:
                r = cur - direct.affine_fit(ref[ok], cur, direct.huber_weights(r, k))
            a = np.stack([s[:, 1] * fx * zi, s[:, 2] * fy * zi,
                          -(s[:, 1] * fx * Xt[:, 0] + s[:, 2] * fy * Xt[:, 1]) * zi * zi], 1)
            J = np.concatenate([a, np.cross(Xt, a)], 1)
            Jw = J * direct.huber_weights(r, k)[:, None]
            H = (J * (np.abs(r) <= k)[:, None]).T @ J if newton else Jw.T @ J
            g = Jw.T @ r
            H[np.diag_indices(6)] *= 1.0 + cfg.damping
            xi = -np.linalg.solve(H + 1e-12 * np.eye(6), g)
            dT = np.eye(4)
            dT[:3, :3] = axis_angle_to_rot(xi[3:])
            dT[:3, 3] = xi[:3]
            M = dT @ M
            taken.append(xi)
            if np.abs(xi).max() < cfg.stop_step:
                break
        return M

    return align_level


def track(seq, cfg: DirectConfig) -> np.ndarray:
    odo = DirectOdometry(seq.calib, cfg)
    return np.array([odo.step(seq.image(i), seq.scan(i)) for i in range(len(seq))])


def report(steps: dict, iterations: tuple[int, ...]) -> None:
    for (width, solves), cap in zip(sorted(steps.items()), iterations):  # both coarse to fine
        counts = np.array([len(s) for s in solves])
        at = [np.median([np.abs(s[j - 1]).max() for s in solves if len(s) >= j]) if counts.max() >= j else np.nan
              for j in AT]
        # from the third step on: the first steps of a level still turn as the threshold settles
        cosines = [np.median([a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-30) for a, b in zip(s[2:], s[3:])])
                   for s in solves if len(s) > 3]
        cosine = f"{np.median(cosines):.2f}" if cosines else "n/a (no solve took four steps)"
        print(f"level {width} px wide: {len(solves)} solves, {counts.mean():.1f} steps on average, "
              f"{(counts == cap).mean():.0%} take all {cap}; median step at "
              + ", ".join(f"{j}: {x:.0e}" for j, x in zip(AT, at))
              + f"; median cosine of consecutive steps from the third on {cosine}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("drive", type=Path)
    ap.add_argument("--newton", action="store_true")
    ap.add_argument("--iters", default=None, help="steps per level, coarse to fine (default: the bundled model's)")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    seq = open_sequence(a.drive)
    cfg = DirectConfig.of_model(load_manifest(bundled_model_dir())["model_config"])
    if a.iters:
        cfg = replace(cfg, iterations=tuple(int(x) for x in a.iters.split(",")))
    steps: dict = collections.defaultdict(list)
    original = direct.align_level
    direct.align_level = recording_align_level(steps, a.newton)
    try:
        poses = track(seq, cfg)
    finally:
        direct.align_level = original
    report(steps, cfg.iterations)
    if a.out:
        write_poses(a.out, poses)
        print(f"{len(poses)} poses in {a.out}")
    if not a.newton and not a.iters:
        diff = np.abs(track(seq, cfg) - poses).max()
        print(f"the recorded copy against the tracker itself: largest pose difference {diff:.1e}")
        if diff > 1e-6:
            raise SystemExit("the recorded copy of the step no longer matches d3lvo_deploy.direct.align_level")


if __name__ == "__main__":
    main()
