"""A learned choice between the weighted and the classical pose, against the thresholds that ship.

    python scripts/learned_choice.py --cache DIR --fit DRIVE... --score DRIVE...

The bundled graph keeps the classical pose of a pair unless its photometric test (the gain and
the rotation between the two poses, under the cap on the share of distrusted points) or frame t's
scan (the weighted pose's scan error below 0.7 times the classical one's) says otherwise: four
hand-set thresholds. Here a logistic regression reads the same numbers per pair (the gain, the
rotation and translation between the poses, the distrusted share, both scan-error ratios, the
gain's significance) and is fitted on the `--fit` drives to tell where the weighted pose is the
closer to the ground truth (translation error plus 0.1 m per degree of rotation error), each pair
weighted by how much the choice matters there (the difference of the two errors).

Prints, on the `--fit` drives, each threshold on the fitted probability alone, and beside what
ships (ships or p > th, ships and p > th); picks the rule by the criterion the shipped thresholds
were chosen by (static drives' t_rel summed at most the classical mode's, higher on at most 4, then
the largest smallest cut on the traffic drives); then scores, on the `--score` drives, what ships,
the rule picked, the weighted pose always, and a per-pair oracle (the pose closer to the ground
truth on each pair, by the same error): what a choice that knew each pair's errors would keep,
not a bound on t_rel (drift adds up over pairs, so a drive can score better with other picks).

Reads the per-pair records of `scripts/selection_rules.py --quick --cache DIR` (the bundled
checkpoint's), recording those that are missing (torch, one thread, about a minute per drive).
Needs the `[train]` (torch) and `[analysis]` (scikit-learn) extras.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from selection_rules import (Drive, photometric_test, recorded_pairs, rule_scores, score,  # noqa: E402
                             with_cap_or_scan)

from d3lvo_deploy.bundled import bundled_model_dir  # noqa: E402
from d3lvo_deploy.geometry import change_frame, rotation_angle_precise  # noqa: E402
from d3lvo_deploy.manifest import load_manifest  # noqa: E402
from models.point_solver import NO_EVIDENCE  # noqa: E402

LEVER = 0.1  # m of translation error per degree of rotation error, in a pair's label
THRESHOLDS = (0.5, 0.7, 0.9, 0.95)
BESIDE = (0.3, 0.5, 0.7, 0.9, 0.95)


def log_ratio(p: dict, name: str) -> tuple[float, float]:
    """log(W's scan error / C's), and 1 where the scan judges (0, 0 where a pose puts no trusted point on a return)."""
    w, c = p[f"{name}_W"], p[f"{name}_C"]
    if max(w, c) >= NO_EVIDENCE:
        return 0.0, 0.0
    return float(np.log(max(w, 1e-9) / max(c, 1e-9))), 1.0


def features(p: dict) -> list[float]:
    scan, judged = log_ratio(p, "scan")
    return [np.arcsinh(p["gain"] / 1e-3), p["rotation"] / 0.05, np.log10(np.linalg.norm(p["W"][:3, 3] - p["C"][:3, 3]) + 1e-5),
            p["share"], scan, log_ratio(p, "scan_all")[0], judged, float(np.clip(p["significance"], -20, 20)) / 5]


def shipped_rule(config: dict):
    """The bundled graph's choice with its own thresholds (`pt_select`, `pt_select_rotation`,
    `pt_select_share`, `pt_select_scan_pass`, read from its manifest): the photometric test under
    the cap on the distrusted share, or the scan's pass."""
    return with_cap_or_scan(photometric_test(config["pt_select"], config["pt_select_rotation"]),
                            config["pt_select_share"], config["pt_select_scan_pass"])


def pair_errors(p: dict, gt: np.ndarray, T: np.ndarray) -> tuple[float, float]:
    """Each pose's error against the ground-truth motion: translation m + LEVER x rotation deg."""
    out = []
    for A in (p["W"], p["C"]):
        E = np.linalg.inv(change_frame(A, T)) @ gt
        out.append(float(np.linalg.norm(E[:3, 3]) + LEVER * np.degrees(rotation_angle_precise(E[:3, :3]))))
    return out[0], out[1]


def fit(X: np.ndarray, y: np.ndarray, w: np.ndarray, l2: float = 1e-2):
    """Weighted, L2-regularised logistic regression (scikit-learn) on standardised features;
    returns the probability and the coefficients (intercept last)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    model = make_pipeline(StandardScaler(), LogisticRegression(C=1 / l2, max_iter=1000, tol=1e-10))
    model.fit(X, y, logisticregression__sample_weight=w / w.mean())
    lr = model[-1]
    return (lambda X: model.predict_proba(X)[:, 1]), np.r_[lr.coef_[0], lr.intercept_]


def main(cache: Path, fit_drives: list[str], score_drives: list[str]) -> None:
    torch.set_num_threads(1)
    shipped = shipped_rule(load_manifest(bundled_model_dir())["model_config"])
    pairs = recorded_pairs(fit_drives + score_drives, bundled_model_dir() / "default.pt", True, cache)
    info, labels = {}, {}
    for d in pairs:
        info[d] = Drive.open(d)
        g = info[d].gt.poses
        labels[d] = [pair_errors(p, np.linalg.inv(g[i]) @ g[i + 1], info[d].T_cam0_cam2) for i, p in enumerate(pairs[d])]
    X = np.array([features(p) for d in fit_drives for p in pairs[d]])
    errs = np.array([e for d in fit_drives for e in labels[d]])
    prob, coef = fit(X, (errs[:, 0] < errs[:, 1]).astype(float), np.abs(errs[:, 0] - errs[:, 1]))
    names = "gain rotation translation share scan scan_all judged significance intercept".split()
    print(f"fitted on {len(X)} pairs of {len(fit_drives)} drives; weighted pose the closer on {np.mean(errs[:, 0] < errs[:, 1]):.1%}")
    print("coefficients (standardised features): " + ", ".join(f"{n} {c:+.3f}" for n, c in zip(names, coef)))
    for d in pairs:  # each pair's fitted probability, and whether its weighted pose is the closer
        for p, q, (w, c) in zip(pairs[d], prob(np.array([features(p) for p in pairs[d]])), labels[d]):
            p["p"], p["closer"] = float(q), w < c
    classical = {d: score(info[d], [p["C"] for p in pairs[d]])[0] for d in pairs}

    def row(name: str, drives: list[str], keep) -> tuple[float, int, float, dict]:
        _, static, cut = rule_scores(info, pairs, classical, keep, drives)
        static = list(static.values())
        text = f"{name:30s} static: sum {sum(static):+.4f}, higher on {sum(x > 1e-4 for x in static)}, " \
               f"lower on {sum(x < -1e-4 for x in static)}"
        if cut:
            text += f"; traffic: cut mean {100 * np.mean(list(cut.values())):.1f} %, smallest {100 * min(cut.values()):.1f} %"
        print(text, flush=True)
        return sum(static), sum(x > 1e-4 for x in static), min(cut.values(), default=0.0), cut

    rules = {"ships": shipped}
    rules.update({f"p > {t}": (lambda ps, i, t=t: ps[i]["p"] > t) for t in THRESHOLDS})
    rules.update({f"ships or p > {t}": (lambda ps, i, t=t: shipped(ps, i) or ps[i]["p"] > t) for t in BESIDE})
    rules.update({f"ships and p > {t}": (lambda ps, i, t=t: shipped(ps, i) and ps[i]["p"] > t) for t in BESIDE})
    print(f"on the {len(fit_drives)} drives fitted on:")
    fitted = {name: row(name, fit_drives, keep) for name, keep in rules.items()}
    eligible = {n: r for n, r in fitted.items() if n != "ships" and r[0] <= 0 and r[1] <= 4}
    if not eligible:
        print("no learned rule meets the criterion (static sum <= 0, higher on <= 4)")
        return
    best = max(eligible, key=lambda n: eligible[n][2])
    print(f"picked: {best} (smallest traffic cut {100 * eligible[best][2]:.1f} % against {100 * fitted['ships'][2]:.1f} % "
          "for what ships)")
    print(f"on the {len(score_drives)} drives scored:")
    cuts = {name: row(name, score_drives, keep)[3] for name, keep in (
        ("ships", shipped), (best, rules[best]), ("weighted always", lambda ps, i: True),
        ("oracle per pair", lambda ps, i: ps[i]["closer"]))}
    print("traffic cut % per drive (ships / picked / weighted always / oracle): " + "  ".join(
        f"{Path(d).name}: " + "/".join(f"{100 * c[d]:.0f}" for c in cuts.values()) for d in cuts["ships"]))


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cache", type=Path, required=True, help="selection_rules.py's record folder")
    parser.add_argument("--fit", nargs="+", required=True, help="drives the regression is fitted and its rule picked on")
    parser.add_argument("--score", nargs="+", required=True, help="drives the rules are scored on once")
    args = parser.parse_args()
    for d in args.fit + args.score:
        if not (Path(d) / "poses.txt").is_file():
            sys.exit(f"{d}: no poses.txt, the ground truth this script scores against")
    both = {Path(d).resolve() for d in args.fit} & {Path(d).resolve() for d in args.score}
    if both:
        sys.exit(f"{sorted(both)[0]}: in both --fit and --score; a drive fitted on scores nothing held out")
    main(args.cache, args.fit, args.score)
