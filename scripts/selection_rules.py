"""Choose `pt_select`, `pt_select_rotation` and the scan's judgement (`pt_select_scan[_pass]`) on validation drives.

    python scripts/selection_rules.py [--ckpt CKPT] [--quick] [--cache DIR] DRIVE...

Runs the checkpoint once per drive (torch, one thread) and records, per pair, the weighted and the
classical solve's poses and the consensus gain. Each pair starts from the weighted pose whatever is
kept, so every rule's trajectory is the recorded poses chosen pair by pair: the grid below is
scored without running the network again. Prints, per rule, each drive's t_rel % (ATE m, marked
`ate`, for drives under 100 m), and the sums the choice reads: on static drives the difference
to the classical pose kept always and on how many of their pairs the rule keeps the weighted
pose, on drives with traffic (a `synth.json` with traffic above 0)
the mean and the smallest reduction against it. Beside the grid, at the shipped thresholds, three
more rules: a cap on the share of frame t-1's points the network distrusts (`pt_select_share`,
which ships at 0.7 with the scan's pass), the test passed on the previous pair too (a mover stays
in view for several pairs), and the gain held out:
the weighted solve run again on half of the points (every second one of the list) and scored on
the other half, both ways round, the smaller gain taken (`held_out_gain`). And one that could:
the network's confidence read again with the classical pose as the motion its evidence is
measured against, the weighted pose kept only where it still distrusts some of the points (the
classical pose leaves something unexplained). And frame t's own LiDAR scan as a judge
(`lidar_depth_error` of the points the network trusts, or of all of them, moved by each pose): the
weighted pose kept only where it fits the scan at most so much worse than the classical one, or
also wherever it fits it much better (where the checkpoint's graph reads that scan). `--quick`
leaves out the rules that need one more solve or pass of the network per pair (the gain held out,
the confidence against the classical pose). Last, what ships (the cap, or the scan's pass), its
photometric side asked for more: a test passed on M of the last K pairs, a share distrusted on
average over the last K pairs, or a gain that stands out from its own spread over the trusted
points (its mean in standard errors of that mean, `gain_significance`). `shipped` in a rule's
name: the photometric test at `pt_select` 0.005, `pt_select_rotation` 0.05 (chosen without the
scan gate; with it the bundled model ships 0.003, the `ships at` rows), without the cap and the
scan's pass unless the name says so; `ships`: the cap and the scan's pass beside that test. And the
grid of thresholds again, each with what ships beside the photometric test (the cap at 0.7, or the
scan's pass at 0.7). And what ships with a memory (`as it ships`: the bundled model's thresholds,
`pt_select` 0.003, with the cap and the scan's pass): the weighted pose held on for H more pairs
after each pair it keeps it on (what `pt_select_hold` H does in the graph and the runtime), or
held for as long as frame t's scan fits it at most v times worse than the classical pose, or as
long as the network distrusts at least a share of the points (`latched`). `--cache DIR` keeps
each drive's record (keyed by the checkpoint's hash and whether `--quick`), so that scoring the
rules on other drives, or again, runs no network twice;
the key names the drive's folder, not its content: empty DIR when a drive is rendered again.
"""

from __future__ import annotations

import hashlib
import itertools
import pickle
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.evaluation import evaluate
from d3lvo_deploy.geometry import accumulate, change_frame, rotation_angle_precise
from d3lvo_deploy.points import SCAN_DEPTH_INPUT
from d3lvo_deploy.poses import Trajectory, read_poses
from d3lvo_deploy.sequence import KittiSequence
from d3lvo_deploy.synth.generator import drive_traffic
from models import pose_points
from models.checkpoint import build_model, load_checkpoint
from models.point_solver import NO_EVIDENCE, consensus_gain, msac_gains, solve
from models.predict import predict_sequence

GAINS = (0.003, 0.005, 0.0075, 0.01, 0.02)
ROTATIONS = (0.0, 0.04, 0.05, 0.06, 0.08, 0.1)  # degrees; 0: off
SHIPPED = (0.005, 0.05)  # `shipped` in a rule's name: the thresholds chosen without the scan gate
SHARES = (0.8, 0.7, 0.6, 0.5)  # the most of frame t-1's points the network may distrust
HELD_OUT = (0.0, 0.002, 0.005, 0.01)
UNEXPLAINED = (0.05, 0.1, 0.15, 0.2, 0.3)  # the least share distrusted against the classical pose
SCAN_VETO = (1.0, 1.1, 1.25, 1.5)  # the weighted pose's scan error at most this times the classical one's
SCAN_PASS = (0.5, 0.7, 0.85)  # ... or kept wherever its scan error is below this times the classical one's
SIGNIFICANCE = (2, 3, 5, 8)  # the gain's mean over the trusted points in standard errors of that mean
RECENT = ((3, 2), (5, 2), (5, 3), (10, 2))  # (K, M): the photometric test passed on M of the last K pairs
RECENT_SHARE = ((5, 0.3), (10, 0.3), (10, 0.35))  # (K, s): the network distrusted s on average over K pairs
AS_SHIPPED = (0.003, 0.05)  # the bundled model's pt_select and pt_select_rotation (with the scan gate)
HOLD = (1, 2, 4, 9)  # the weighted pose kept on the H pairs after each one the selection keeps it on
LATCH_SCAN = (1.0, 1.1)  # ... kept while frame t's scan fits it at most this times worse than the classical pose
LATCH_SHARE = (0.1, 0.2, 0.3)  # ... kept while the network distrusts at least this share of the points


def distrusted_share(weight: torch.Tensor, mask: torch.Tensor) -> float:
    """`pose_points.distrusted_share` of batch row 0."""
    return float(pose_points.distrusted_share(weight, mask)[0])


def held_out_gain(pose: pose_points.PointPose, init: torch.Tensor, solver: dict, weight: torch.Tensor,
                   classical: torch.Tensor) -> float:
    """`consensus_gain` where the weighted pose has not seen the points it is scored on: the weighted
    solve again on the even points of the list, scored against the classical pose on the odd ones,
    and the other way round; the smaller of the two (batch row 0). The shipped gain scores the
    weighted pose on the points it was fitted to, which a confidence that doubts most of a static
    scene turns into a gain of its own."""
    grey1, stack2 = pose.pyramids(solver)
    points, mask, K = solver["points1"], solver["point_mask1"], solver["image_intrinsics"]
    even = (torch.arange(points.shape[1]) % 2 == 0).to(weight.dtype)[None]
    halves = (even, 1.0 - even)
    two = lambda x: pose_points.interleave(x, x)  # noqa: E731
    fitted = solve(grey1, stack2, two(points), pose_points.interleave(weight * halves[0], weight * halves[1]),
                   two(K), two(init), pose.settings, mask=two(mask))[-1]
    return min(float(consensus_gain(fitted[i : i + 1], classical, grey1[0], stack2[0], points,
                                    weight * halves[1 - i], K)[0]) for i in (0, 1))


def gain_significance(pose: pose_points.PointPose, A: torch.Tensor, C: torch.Tensor, solver: dict,
                      weight: torch.Tensor) -> float:
    """The consensus gain in standard errors of its mean over the trusted points (batch row 0): a
    mover pulls the classical pose off every static point alike, where a weighted pose that merely
    fits its own points gains on some and loses on others."""
    grey1, stack2 = pose.pyramids(solver)
    gains, trusted = msac_gains(A, C, grey1[0], stack2[0], solver["points1"], weight, solver["image_intrinsics"])
    g = gains[0][trusted[0] > 0].double()
    if len(g) < 3 or float(g.std()) == 0.0:
        return 0.0
    return float(g.mean() / (g.std() / len(g) ** 0.5))


def scan_errors(A: torch.Tensor, C: torch.Tensor, solver: dict, weight: torch.Tensor) -> dict:
    """`PointPose.scan_errors` of both poses (batch row 0): over the points the network trusts, as
    the graph's judge counts them, and over every point of the list."""
    out = {}
    for name, w in (("scan", weight), ("scan_all", solver["point_mask1"])):
        fits = pose_points.PointPose.scan_errors(A, C, solver, w)[0]
        out[f"{name}_W"], out[f"{name}_C"] = float(fits[0]), float(fits[1])
    return out


def record_pairs(model, drive: str, quick: bool = False) -> list[dict]:
    """Per pair: gain, weighted pose W and classical pose C (image_2, frame t in frame t-1), the
    share of the points the network distrusts, both poses' scan errors (`scan_errors`), and unless
    `quick` the gain held out and the share it distrusts against C."""
    pairs: list[dict] = []
    forward = pose_points.PointPose.forward

    def recording(self, *args):
        out = forward(self, *args)
        if "consensus_gain" in out:
            weight, solver = out["point_weights"], args[-1]
            pair = dict(gain=float(out["consensus_gain"][0]), W=out["start_next"][0].double().numpy(),
                        C=out["classical"][0].double().numpy(), share=distrusted_share(weight, solver["point_mask1"]),
                        significance=gain_significance(self, out["start_next"], out["classical"], solver, weight))
            if SCAN_DEPTH_INPUT in solver:  # the checkpoint's graph reads frame t's scan
                pair.update(scan_errors(out["start_next"], out["classical"], solver, weight))
            if not quick:
                pair.update(held_out=held_out_gain(self, args[7], solver, weight, out["classical"]),
                            unexplained=float(self.distrusted_against(*args[:7], out["classical"], solver)[0]))
            pairs.append(pair)
        return out

    pose_points.PointPose.forward = recording
    try:
        predict_sequence(model, drive)
    finally:
        pose_points.PointPose.forward = forward
    return pairs


@dataclass
class Drive:
    """What scoring a drive reads from its folder, read once for every rule."""
    T_cam0_cam2: np.ndarray
    gt: Trajectory
    traffic: bool

    @classmethod
    def open(cls, drive: str) -> "Drive":
        return cls(KittiSequence.open(drive).calib.T_cam0_cam2, read_poses(Path(drive) / "poses.txt"),
                   (drive_traffic(drive) or 0) > 0)


def score(drive: Drive, relatives: list[np.ndarray]) -> tuple[float, str]:
    rel = np.array([change_frame(A, drive.T_cam0_cam2) for A in relatives])
    r = evaluate(drive.gt, Trajectory.from_poses(accumulate(rel)))
    return (r.t_rel, "") if r.t_rel is not None else (r.ate, " ate")


def cached_pairs(model, drive: str, quick: bool, cache: Path | None, key: str) -> list[dict]:
    """`record_pairs`, read from `cache` where this checkpoint's record of the drive is kept."""
    path = None if cache is None else record_path(cache, drive, key, quick)
    if path is not None and path.is_file():
        return pickle.loads(path.read_bytes())
    pairs = record_pairs(model, drive, quick)
    if path is not None:
        cache.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".part")
        tmp.write_bytes(pickle.dumps(pairs))
        tmp.replace(path)
    return pairs


def record_path(cache: Path, drive: str, key: str, quick: bool) -> Path:
    return cache / f"{Path(drive).resolve().name}-{key}{'-quick' if quick else ''}.pkl"


def recording_model(checkpoint: Path):
    """The checkpoint with both solves kept on every pair (what is kept is chosen rule by rule)."""
    ck = load_checkpoint(checkpoint)
    ck["config"] = replace(ck["config"], pt_select=min(GAINS), pt_select_rotation=0.0, pt_select_share=1.0)
    return build_model(ck)


def recorded_pairs(drives: list[str], checkpoint: Path, quick: bool = False,
                   cache: Path | None = None) -> dict[str, list[dict]]:
    """Per drive, its pairs' records (`cached_pairs`; the network built only where one is missing),
    each with the rotation between its weighted and classical pose (degrees)."""
    key = hashlib.sha256(checkpoint.read_bytes()).hexdigest()[:12]
    model, pairs = None, {}
    for drive in drives:
        if model is None and (cache is None or not record_path(cache, drive, key, quick).is_file()):
            model = recording_model(checkpoint)
        pairs[drive] = cached_pairs(model, drive, quick, cache, key)
        for p in pairs[drive]:
            D = p["C"][:3, :3].T @ p["W"][:3, :3]
            p["rotation"] = float(np.degrees(rotation_angle_precise(D)))
    return pairs


def rule_scores(info: dict[str, Drive], pairs: dict[str, list[dict]], classical: dict[str, float], keep,
                drives: list[str]) -> tuple[dict, dict, dict]:
    """A rule's (t_rel or ATE, unit) per drive, and against the classical pose kept always: the
    static drives' differences and the traffic drives' cuts."""
    scores = {d: score(info[d], [p["W"] if keep(pairs[d], i) else p["C"] for i, p in enumerate(pairs[d])])
              for d in drives}
    static = {d: scores[d][0] - classical[d] for d in drives if not info[d].traffic}
    cut = {d: 1 - scores[d][0] / classical[d] for d in drives if info[d].traffic}
    return scores, static, cut


def photometric_test(g: float, r: float):
    """The graph's photometric test as a rule: the consensus gain above `g` and the rotation between
    the two poses above `r` degrees."""
    return lambda ps, i: ps[i]["gain"] > g and ps[i]["rotation"] > r


def scan_fits(ps, i, n: str, r: float, strict: bool) -> bool | None:
    """W's scan error at most (below, `strict`) r times C's; None where a pose puts no trusted
    point on a return (the graph's `NO_EVIDENCE`): there the scan does not judge."""
    w, c = ps[i][f"{n}_W"], ps[i][f"{n}_C"]
    if max(w, c) >= NO_EVIDENCE:
        return None
    return w < r * c if strict else w <= r * c


def with_cap_or_scan(photometric, share: float = 0.7, scan_pass: float = 0.7):
    """What ships beside a photometric test: the test under the cap on the distrusted share, or
    frame t's scan's pass (W's scan error below `scan_pass` times C's)."""
    return lambda ps, i: (photometric(ps, i) and ps[i]["share"] <= share) or bool(scan_fits(ps, i, "scan", scan_pass, True))


def held_after(start, h: int):
    """The weighted pose kept where `start` keeps it and on the `h` pairs after each such pair."""
    return lambda ps, i: any(start(ps, j) for j in range(max(0, i - h), i + 1))


def latched(start, stay):
    """A choice with memory: the weighted pose kept where `start` keeps it, and on each following
    pair while `stay` holds (a vehicle stays in view for a while; once the selection has seen it,
    weaker evidence keeps the weighted pose). Each drive's choices in order, kept per drive."""
    memo: dict[int, list[bool]] = {}

    def keep(ps, i):
        seq = memo.setdefault(id(ps), [])
        while len(seq) <= i:
            j = len(seq)
            seq.append(bool(start(ps, j) or (j > 0 and seq[j - 1] and stay(ps, j))))
        return seq[i]
    return keep


def main(drives: list[str], checkpoint: Path, quick: bool = False, cache: Path | None = None) -> None:
    for drive in drives:
        if not (Path(drive) / "poses.txt").is_file():
            sys.exit(f"{drive}: no poses.txt, the ground truth this script scores against")
    torch.set_num_threads(1)
    pairs = recorded_pairs(drives, checkpoint, quick, cache)
    for drive in drives:
        print(f"recorded {Path(drive).name}: {len(pairs[drive])} pairs", flush=True)
    info = {d: Drive.open(d) for d in drives}
    classical = {d: score(info[d], [p["C"] for p in pairs[d]])[0] for d in drives}

    rules = [("classical always", lambda ps, i: False), ("weighted always", lambda ps, i: True)]
    rules += [(f"pt_select {g} pt_select_rotation {r}", photometric_test(g, r)) for g, r in itertools.product(GAINS, ROTATIONS)]
    shipped = photometric_test(*SHIPPED)
    rules += [(f"shipped, distrusted share <= {f}", lambda ps, i, f=f: shipped(ps, i) and ps[i]["share"] <= f)
              for f in SHARES]
    rules.append(("shipped, passed on the last pair too",
                  lambda ps, i: shipped(ps, i) and i > 0 and shipped(ps, i - 1)))
    if not quick:
        rules += [(f"shipped, held-out gain > {g}", lambda ps, i, g=g: shipped(ps, i) and ps[i]["held_out"] > g)
                  for g in HELD_OUT]
        rules += [(f"held-out gain > {g} pt_select_rotation {SHIPPED[1]}",
                   lambda ps, i, g=g: ps[i]["held_out"] > g and ps[i]["rotation"] > SHIPPED[1]) for g in HELD_OUT]
        rules += [(f"shipped, distrusted against C > {f}",
                   lambda ps, i, f=f: shipped(ps, i) and ps[i]["unexplained"] > f) for f in UNEXPLAINED]

    has_scan = all("scan_W" in p for ps in pairs.values() for p in ps)  # the checkpoint's graph reads it
    for scan in ("scan", "scan_all") if has_scan else ():
        rules += [(f"shipped, {scan} W <= {r} C", lambda ps, i, r=r, n=scan: shipped(ps, i)
                   and scan_fits(ps, i, n, r, False) is not False) for r in SCAN_VETO]
        rules += [(f"shipped or {scan} W < {r} C", lambda ps, i, r=r, n=scan: shipped(ps, i)
                   or bool(scan_fits(ps, i, n, r, True))) for r in SCAN_PASS]
        rules += [(f"{scan} W < {r} C alone", lambda ps, i, r=r, n=scan: bool(scan_fits(ps, i, n, r, True)))
                  for r in SCAN_PASS]
        # the shipped selection (the photometric test, or the scan's pass at 0.7) with a cap on the
        # share of points the network distrusts on the photometric side
        rules += [(f"shipped, share <= {f}, or {scan} W < 0.7 C", lambda ps, i, f=f, n=scan:
                   (shipped(ps, i) and ps[i]["share"] <= f) or bool(scan_fits(ps, i, n, 0.7, True))) for f in SHARES]
        rules += [(f"shipped and {scan} W <= {v} C, or W < {r} C", lambda ps, i, v=v, r=r, n=scan:
                   (shipped(ps, i) and scan_fits(ps, i, n, v, False) is not False) or bool(scan_fits(ps, i, n, r, True)))
                  for v, r in itertools.product(SCAN_VETO[:2], SCAN_PASS)]
    if has_scan:
        # what ships (the photometric test with the cap at 0.7, or the scan's pass at 0.7), the
        # photometric side asked for more: several pairs read together (vehicles stay in view for a
        # while, a false detection comes and goes), or a gain that stands out from its own spread
        capped = lambda ps, i: shipped(ps, i) and ps[i]["share"] <= 0.7  # noqa: E731
        last = lambda i, k: range(max(0, i - k + 1), i + 1)  # noqa: E731

        def ships(extra):
            return with_cap_or_scan(lambda ps, i: shipped(ps, i) and extra(ps, i))

        rules += [(f"ships, and passed on {m} of the last {k} pairs", ships(lambda ps, i, k=k, m=m:
                   sum(capped(ps, j) for j in last(i, k)) >= m)) for k, m in RECENT]
        rules += [(f"ships, and distrusted {f} over the last {k} pairs", ships(lambda ps, i, k=k, f=f:
                   np.mean([ps[j]["share"] for j in last(i, k)]) >= f)) for k, f in RECENT_SHARE]
        rules += [(f"ships, and its gain above {z} standard errors", ships(lambda ps, i, z=z:
                   ps[i]["significance"] > z)) for z in SIGNIFICANCE]
        # what ships with memory: the weighted pose held on after the selection keeps it, for a few
        # pairs, or as long as the scan does not fit it worse or the network still distrusts points
        as_ships = with_cap_or_scan(photometric_test(*AS_SHIPPED))
        rules.append(("as it ships", as_ships))
        rules += [(f"as it ships, held {h} pairs after", held_after(as_ships, h)) for h in HOLD]
        rules += [(f"as it ships, held while scan W <= {v} C", latched(as_ships, lambda ps, i, v=v:
                   scan_fits(ps, i, "scan", v, False) is not False)) for v in LATCH_SCAN]
        rules += [(f"as it ships, held while distrusted >= {f}", latched(as_ships, lambda ps, i, f=f:
                   ps[i]["share"] >= f)) for f in LATCH_SHARE]
        # the photometric test's thresholds chosen again with what ships beside it
        rules += [(f"ships at pt_select {g} pt_select_rotation {r}", with_cap_or_scan(photometric_test(g, r)))
                  for g, r in itertools.product(GAINS, ROTATIONS)]
    print("drives: " + " ".join(Path(d).name for d in drives))
    for name, keep in rules:
        scores, static, cut = rule_scores(info, pairs, classical, keep, drives)
        static, cut = list(static.values()), list(cut.values())
        kept = [keep(pairs[d], i) for d in drives if not info[d].traffic for i in range(len(pairs[d]))]
        summary = f"static: sum {sum(static):+.4f}, higher on {sum(x > 1e-4 for x in static)}, lower on " \
                  f"{sum(x < -1e-4 for x in static)}, weighted kept on {sum(kept)} of {len(kept)} pairs" \
            if static else ""
        if cut:
            summary += f"; traffic: cut mean {100 * np.mean(cut):.1f} %, smallest {100 * min(cut):.1f} %"
        print(f"{name:48s} {summary} | " + " ".join(f"{s:.3f}{unit}" for s, unit in scores.values()), flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    quick = "--quick" in args
    args = [a for a in args if a != "--quick"]
    cache = None
    if "--cache" in args:
        i = args.index("--cache")
        if i + 1 >= len(args):
            sys.exit("--cache needs a folder")
        cache, args = Path(args[i + 1]), args[:i] + args[i + 2:]
    ckpt = bundled_model_dir() / "default.pt"
    if args[:1] == ["--ckpt"] and len(args) > 1:
        ckpt, args = Path(args[1]), args[2:]
    if not args:
        sys.exit(__doc__)
    if not ckpt.is_file():
        sys.exit(f"{ckpt}: no such checkpoint")
    main(args, ckpt, quick, cache)
