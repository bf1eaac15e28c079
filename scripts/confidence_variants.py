"""How the bundled model's confidence becomes a point weight: variants measured in torch, without retraining.

On static drives the bundled network's per-pair rotation error is a little higher than its
classical mode's (docs/evaluation.md). This script asks whether a different use of the same
confidence closes that gap without giving up the gain with traffic. Each variant runs the bundled
weights (or `--ckpt`'s) over whole drives (`models.predict.predict_sequence`) and prints `d3lvo
eval`'s figures:

- `conf`: the shipped weight, the point's confidence (the weighted pose; every variant but
  `pt_select:T` and `kept-start:T` runs with `pt_select = 0`);
- `ones`: every weight 1, the classical mode;
- `lin:A:B`: (conf - A) / (B - A) clipped to [0, 1] (`pt_conf_full=C` is `lin:0:C`);
- `strong:T`: only confidences below T kept, the rest 1; `mild:T`: confidences below T set to 1;
- `evidence-at-classical`: the confidence net reads its evidence against the motion a classical
  solve (every weight 1) finds from the same constant-velocity start, instead of that start (one
  more solve per pair);
- `evidence-at-network`: two passes; the second reads the evidence against the motion the first
  (the shipped weights) found, and solves again from there;
- `open:K`: the map of p(moving) = 1 - confidence opened (eroded, then dilated) with a KxK window
  before the points read it: thin detections along edges go, blobs as wide as K cells stay;
- `select:C:T`: the confidence-weighted and the classical pose per pair, the one with the lower
  MSAC cost (residuals truncated at C robust sigmas, over the points of confidence T or more)
  kept (one more solve per pair);
- `pt_select:T`: the model's own setting `pt_select=T`: the classical pose unless the weighted one
  explains the points the network trusts better by more than T (`point_solver.consensus_gain`;
  one more solve per pair);
- `kept-start:T`: `pt_select:T`, but each pair starts from the pose kept at the previous pair
  rather than from its weighted pose (the graph's `start_next`, what the bundled model does);
- `depth-guided:S`: each point reads the confidence of the cells around it that lie at its own
  depth (within a relative spread S), not a blend across a vehicle's edge;
- `posterior:C`: per solver step, the confidence as a prior that the point is static, updated by
  its residual (a Huber-shaped likelihood against a uniform one of density C on the [0, 1] grey
  scale).

    .venv/bin/python scripts/confidence_variants.py [--ckpt CHECKPOINT] VARIANT DRIVE [DRIVE ...]
    # ~40 s per 200 frames on an AMD EPYC (AVX-512), one thread
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.evaluation import evaluate
from d3lvo_deploy.poses import Trajectory, read_poses
from models import point_solver, pose_points
from models.checkpoint import build_model, load_checkpoint
from models.point_solver import HUBER_K, MAD_TO_SIGMA, solve
from models.predict import predict_sequence


Remap = Callable[[torch.Tensor], torch.Tensor]
REMAPS = {"ones": 0, "lin": 2, "strong": 1, "mild": 1}  # name: how many numbers follow it
OTHERS = {"conf": 0, "open": 1, "evidence-at-classical": 0, "evidence-at-network": 0, "posterior": 1, "select": 2,
          "pt_select": 1, "kept-start": 1, "depth-guided": 1}
CHOICES: list[float] = []  # `select`, `pt_select`: per pair, 1 where the classical pose was kept


def parse(variant: str) -> tuple[str, list[float]]:
    """Name and numbers of a variant, or exit with what is wrong with it."""
    name, *args = variant.split(":")
    count = {**REMAPS, **OTHERS}.get(name)
    if count is None:
        sys.exit(f"unknown variant {variant!r}: conf, ones, lin:A:B, strong:T, mild:T, evidence-at-classical, evidence-at-network, open:K, posterior:C, select:C:T, pt_select:T, kept-start:T, depth-guided:S")
    try:
        numbers = [float(x) for x in args]
    except ValueError:
        numbers = []
    if len(numbers) != count or len(args) != count:
        sys.exit(f"variant {variant!r}: {name} takes {count} number(s) after its name, separated by ':'")
    if name == "lin" and not numbers[0] < numbers[1]:
        sys.exit(f"variant {variant!r}: lin:A:B needs A < B (the ramp from weight 0 at A to 1 at B)")
    if name == "open" and not (numbers[0] >= 1 and numbers[0] % 2 == 1):
        sys.exit(f"variant {variant!r}: the window K must be an odd whole number of cells")
    if name == "select" and not numbers[0] > 0:
        sys.exit(f"variant {variant!r}: the truncation C (robust sigmas) must be above 0")
    if name in ("pt_select", "kept-start") and not 0 < numbers[0] < 1:
        sys.exit(f"variant {variant!r}: the threshold T must be in (0, 1)")
    if name == "depth-guided" and not numbers[0] > 0:
        sys.exit(f"variant {variant!r}: the relative depth spread S must be above 0")
    if name == "posterior" and not numbers[0] > 0:
        sys.exit(f"variant {variant!r}: the outlier density C must be above 0")
    return name, numbers


def weight_map(name: str, a: list[float]) -> Remap | None:
    """conf (B,N) -> weight (B,N) for the remapping variants; None for the others."""
    if name == "ones":
        return torch.ones_like
    if name == "lin":
        return lambda c: ((c - a[0]) / (a[1] - a[0])).clamp(0.0, 1.0)
    if name == "strong":
        return lambda c: torch.where(c < a[0], c, torch.ones_like(c))
    if name == "mild":
        return lambda c: torch.where(c < a[0], torch.ones_like(c), c)
    return None


def posterior_steps(density: float) -> Callable:
    """`point_solver.gn_steps` with the weight p / (p + (1 - p) density sigma sqrt(2 pi) exp(rho(r / sigma)))
    in place of p: a point the residual says is an outlier loses its prior weight."""
    gn_steps, huber = point_solver.gn_steps, point_solver.huber_weights_at

    def steps(P, active, Xh, ref, stack, G, f, weight, w_ok, median_mask, *rest):
        def huber_and_posterior(r: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
            sigma = k / HUBER_K
            z = (r / sigma).abs()
            rho = torch.where(z <= HUBER_K, 0.5 * z**2, HUBER_K * z - 0.5 * HUBER_K**2).clamp(max=50.0)
            # gn_steps multiplies by `weight` again: posterior / weight
            return huber(r, k) / (weight + (1 - weight) * density * sigma * math.sqrt(2 * math.pi) * torch.exp(rho))

        point_solver.huber_weights_at = huber_and_posterior
        try:
            return gn_steps(P, active, Xh, ref, stack, G, f, weight, w_ok, median_mask, *rest)
        finally:
            point_solver.huber_weights_at = huber

    return steps


def truncated_cost(A: torch.Tensor, points: torch.Tensor, mask: torch.Tensor, ref: torch.Tensor, grey2: torch.Tensor,
                   K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals (B,N) of frame t-1's points under the relative pose A (B,4,4) in frame t's grey
    at full resolution, and where they are valid (listed, in front, inside)."""
    M = torch.linalg.inv(A)
    r, seen = point_solver.residuals_at(M[:, :3, :3], M[:, None, :3, 3], points, ref, grey2, K)
    return r, seen * (mask > 0).to(r.dtype)


def select_pose(c: float, gate: float) -> None:
    """Two hypotheses per pair, the confidence-weighted pose and the classical one (every weight 1),
    scored as RANSAC's MSAC scores a hypothesis: the sum over the listed points whose confidence is
    at least `gate` (the strong detections of movers left out) of min(r^2, (c sigma)^2), sigma 1.4826 x the smaller of the two median |r|, a point out of view at the cap;
    the lower cost wins, the classical pose on a tie. On a static scene the classical pose, fitted
    to every point, explains them best; where something moves, the pose that ignores it explains
    the static majority."""
    forward = pose_points.PointPose.forward

    def selecting(self, hidden, flow, feat1, feat2, invdepth1, invdepth2, K, init, solver):
        out = forward(self, hidden, flow, feat1, feat2, invdepth1, invdepth2, K, init, solver)
        if solver is None:
            return out
        grey1, stack2 = self.pyramids(solver)
        points, mask, Ki = solver["points1"], solver["point_mask1"], solver["image_intrinsics"]
        classical = solve(grey1, stack2, points, mask, Ki, init, self.settings, mask=mask)[-1]
        ref = point_solver.sample_at(grey1[0], point_solver.project(points, Ki)[0])[:, 0]
        network = out["level_matrices"][-1]
        scored = mask * (out["point_weights"] >= gate).to(mask.dtype)
        (rn, okn), (rc, okc) = [truncated_cost(A, points, scored, ref, stack2[0][:, :1], Ki) for A in (network, classical)]
        sigma = MAD_TO_SIGMA * torch.minimum(point_solver.masked_median(rn.abs(), okn),
                                             point_solver.masked_median(rc.abs(), okc))
        cap = (c * sigma) ** 2
        cost = [torch.where(ok > 0, torch.minimum(r**2, cap), cap).mul(scored).sum(-1) for r, ok in ((rn, okn), (rc, okc))]
        keep = (cost[1] <= cost[0]).to(network.dtype)
        CHOICES.extend(keep.tolist())
        out["level_matrices"] = [*out["level_matrices"][:-1], keep[:, None, None] * classical + (1 - keep[:, None, None]) * network]
        return out

    pose_points.PointPose.forward = selecting


def depth_guided(spread: float) -> None:
    """Each point reads the confidence of the four cells around it (`point_confidence`'s bilinear
    corners) weighted also by how near each cell's depth (the network's completed depth at the
    cell) is to the point's own, exp(-(|z_cell - z| / (spread z))^2): a point beside a vehicle's
    edge takes the confidence of the cells at its own depth, not a blend of vehicle and background."""
    forward, bilinear = pose_points.PointPose.forward, pose_points.PointPose.point_confidence

    def keeping_depth(self, hidden, flow, feat1, feat2, invdepth1, *rest):
        self._invdepth1 = invdepth1
        return forward(self, hidden, flow, feat1, feat2, invdepth1, *rest)

    def guided(self, c, points, K):
        uv, zi, _ = point_solver.project(points, K)
        s = float(2 ** (self.level + 1))
        h, w = c.shape[-2:]
        x, y = (uv[..., 0] / s).clamp(0, w - 1), (uv[..., 1] / s).clamp(0, h - 1)
        x0, y0 = x.floor().clamp(max=w - 2), y.floor().clamp(max=h - 2)
        fx, fy = x - x0, y - y0
        z = 1.0 / zi
        total, norm = torch.zeros_like(x), torch.zeros_like(x)
        for dx, dy, wb in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
            idx = ((y0 + dy) * w + x0 + dx).long()
            cell_c = c.flatten(1).gather(1, idx)
            cell_z = self.cfg.min_depth / self._invdepth1.flatten(1).gather(1, idx).clamp(min=1e-6)
            wt = wb * torch.exp(-(((cell_z - z).abs() / (spread * z)) ** 2))
            total, norm = total + wt * cell_c, norm + wt
        return torch.where(norm > 1e-6, total / norm.clamp(min=1e-6), bilinear(self, c, points, K))

    pose_points.PointPose.forward = keeping_depth
    pose_points.PointPose.point_confidence = guided


def apply_variant(name: str, numbers: list[float]) -> None:
    """Patch the model code for one variant (this process only)."""
    remap = weight_map(name, numbers)
    if remap is not None:
        confidence = pose_points.PointPose.point_confidence
        pose_points.PointPose.point_confidence = lambda self, c, p, K: remap(confidence(self, c, p, K))
    elif name == "open":
        k = int(numbers[0])
        confidence = pose_points.PointPose.point_confidence

        def opened(self, c, p, K):
            pool = lambda x: torch.nn.functional.max_pool2d(x, k, stride=1, padding=k // 2)
            return confidence(self, 1.0 - pool(-pool(-(1.0 - c))), p, K)

        pose_points.PointPose.point_confidence = opened
    elif name == "select":
        select_pose(*numbers)
    elif name == "depth-guided":
        depth_guided(numbers[0])
    elif name == "kept-start":
        forward = pose_points.PointPose.forward

        def kept_start(self, *args):
            out = forward(self, *args)
            out.pop("start_next", None)  # `predict_sequence` then starts from the kept pose
            return out

        pose_points.PointPose.forward = kept_start
    elif name == "posterior":
        point_solver.gn_steps = posterior_steps(numbers[0])
    elif name == "evidence-at-classical":
        forward, logits = pose_points.PointPose.forward, pose_points.PointPose.moving_logits

        def classical_start(self, hidden, flow, feat1, feat2, invdepth1, invdepth2, K, init, solver):
            if solver is not None:
                solved = solve(*self.pyramids(solver), solver["points1"], solver["point_mask1"], solver["image_intrinsics"], init,
                               self.settings)[-1]
                self.moving_logits = lambda *a: logits(self, *a[:-1], solved)
            try:
                return forward(self, hidden, flow, feat1, feat2, invdepth1, invdepth2, K, init, solver)
            finally:
                self.__dict__.pop("moving_logits", None)

        pose_points.PointPose.forward = classical_start
    elif name == "evidence-at-network":
        forward = pose_points.PointPose.forward

        def two_passes(self, hidden, flow, feat1, feat2, invdepth1, invdepth2, K, init, solver):
            out = forward(self, hidden, flow, feat1, feat2, invdepth1, invdepth2, K, init, solver)
            if solver is None:
                return out
            return forward(self, hidden, flow, feat1, feat2, invdepth1, invdepth2, K, out["level_matrices"][-1], solver)

        pose_points.PointPose.forward = two_passes


def record_weights(into: list[np.ndarray]) -> None:
    """Keep each pair's (depth, image row, weight) of the listed points, to say where the weights fall."""
    forward = pose_points.PointPose.forward

    def recording(self, *args):
        out = forward(self, *args)
        if "consensus_gain" in out:
            CHOICES.extend((out["consensus_gain"] <= self.cfg.pt_select).double().tolist())
        if "point_weights" in out:
            solver = args[-1]
            on = solver["point_mask1"][0] > 0
            uv, _, _ = point_solver.project(solver["points1"], solver["image_intrinsics"])
            into.append(np.c_[solver["points1"][0][on][:, 2].numpy(), uv[0][on][:, 1].numpy(),
                              out["point_weights"][0][on].numpy()])
        return out

    pose_points.PointPose.forward = recording


DEPTHS = (0.0, 5.0, 10.0, 20.0, math.inf)


def main(variant: str, drives: list[str], checkpoint: Path) -> None:
    """Run the variant over each drive and print its scores and where its weights fall."""
    name, numbers = parse(variant)
    if not checkpoint.is_file():
        sys.exit(f"{checkpoint}: no such checkpoint")
    for drive in drives:
        if not (Path(drive) / "poses.txt").is_file():
            sys.exit(f"{drive}: no poses.txt, the ground truth this script scores against")
    torch.set_num_threads(1)
    apply_variant(name, numbers)
    pairs: list[np.ndarray] = []
    record_weights(pairs)
    ck = load_checkpoint(checkpoint)
    # every variant but pt_select:T and kept-start:T scores the weighted pose alone (the bundled model keeps the
    # classical pose where the weighted one does not explain the trusted points better)
    ck["config"] = replace(ck["config"], pt_select=numbers[0] if name in ("pt_select", "kept-start") else 0.0,
                           pt_select_rotation=0.0)  # the gain alone, as the model card's tables of these variants
    model = build_model(ck)
    for drive in drives:
        est = predict_sequence(model, drive)
        r = evaluate(read_poses(Path(drive) / "poses.txt"), Trajectory.from_poses(est))
        t_rel = "n/a (under 100 m)" if r.t_rel is None else f"{r.t_rel:.4f} %"
        print(f"{variant} {Path(drive).name}: t_rel {t_rel} rpe_t {r.rpe_t * 1e3:.3f} mm "
              f"rpe_r {r.rpe_r * 1e3:.2f} mdeg ate {r.ate:.3f} m", flush=True)
        z, row, w = np.concatenate(pairs).T
        bins = []
        for lo, hi in zip(DEPTHS[:-1], DEPTHS[1:]):
            within = (z >= lo) & (z < hi)
            if within.any():
                bins.append(f"{f'{lo:g}-{hi:g} m' if hi < math.inf else f'from {lo:g} m'}: {w[within].mean():.3f}")
        print(f"  mean point confidence after the variant's remap (before any Huber or posterior weight) by "
              f"depth: {', '.join(bins)}; below 0.5: {100 * (w < 0.5).mean():.1f} % of {len(w)} points", flush=True)
        edges = np.quantile(row, np.linspace(0.0, 1.0, 5))
        quarters = []
        for lo, hi in zip(edges[:-1], edges[1:]):
            within = (row >= lo) & (row <= hi)
            quarters.append(f"rows {lo:.0f}-{hi:.0f}: {w[within].mean():.3f} (median depth {np.median(z[within]):.1f} m)")
        print(f"  by image row, top to bottom, a quarter of the points each: {', '.join(quarters)}", flush=True)
        pairs.clear()
        if CHOICES:
            print(f"  the classical pose kept in {100 * np.mean(CHOICES):.1f} % of {len(CHOICES)} pairs", flush=True)
            CHOICES.clear()


if __name__ == "__main__":
    args = sys.argv[1:]
    ckpt = bundled_model_dir() / "default.pt"
    if args[:1] == ["--ckpt"] and len(args) > 1:
        ckpt, args = Path(args[1]), args[2:]
    if len(args) < 2:
        sys.exit(__doc__)
    main(args[0], args[1:], ckpt)
