"""Evaluation: trajectories whose errors are computed on paper, real GT files, and published results."""

import math

import numpy as np
import pytest
from conftest import shared_path

from d3lvo_deploy import metrics
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.evaluation import evaluate, evaluate_files
from d3lvo_deploy.geometry import apply_sim3, axis_angle_to_rot, make_se3, relative
from d3lvo_deploy.poses import Trajectory, read_poses


def straight(n, step=1.0):
    """Driving along z at `step` metres per frame."""
    return np.stack([make_se3(np.eye(3), [0, 0, step * i]) for i in range(n)])


# the KITTI devkit's segment lengths (evaluate_odometry.cpp, `lengths[]`), written out here so a
# change to metrics.SEGMENT_LENGTHS cannot move the expectation with it
DEVKIT_LENGTHS = (100, 200, 300, 400, 500, 600, 700, 800)


def expected_segments(n, step=1.0):
    """(first, length, last) of the devkit's segments on a straight line, by hand."""
    out = []
    for first in range(0, n, 10):
        for L in DEVKIT_LENGTHS:
            k = int(math.floor(L / step)) + 1  # first frame strictly beyond L metres
            if first + k < n:
                out.append((first, L, first + k))
    return out


def test_constant_scale_drift_gives_exact_t_rel():
    gt = straight(1000)
    est = straight(1000, 1.01)  # 1 % too long, every segment
    res = evaluate(Trajectory.from_poses(gt), Trajectory.from_poses(est))
    segs = expected_segments(1000)
    assert res.segments == len(segs)
    # t_err of a segment = 0.01 * (last - first) metres, divided by its nominal length
    expect = np.mean([0.01 * (last - first) / L for first, L, last in segs]) * 100
    assert res.t_rel == pytest.approx(expect, rel=1e-5)
    assert res.r_rel == 0.0
    assert res.rpe_t == pytest.approx(0.01, rel=1e-9)


def test_pure_yaw_bias():
    """Estimate = GT positions with a heading that drifts by delta per frame."""
    n, delta = 900, 1e-3
    gt = straight(n)
    est = np.stack([make_se3(axis_angle_to_rot([0, delta * i, 0]), gt[i][:3, 3]) for i in range(n)])
    res = evaluate(Trajectory.from_poses(gt), Trajectory.from_poses(est))
    segs = expected_segments(n)
    r = np.mean([(last - first) * delta / L for first, L, last in segs])
    # E's translation = (I - R(-first*delta)) dp: |.| = 2 sin(first*delta/2) |dp|
    t = np.mean([2 * np.sin(first * delta / 2) * (last - first) / L for first, L, last in segs])
    assert res.r_rel == pytest.approx(np.degrees(r) * 100, rel=1e-3)  # devkit float32 acos
    assert res.t_rel == pytest.approx(t * 100, rel=1e-4)
    assert res.rpe_r == pytest.approx(np.degrees(delta), rel=1e-3)


def test_alignment_undoes_a_similarity():
    rng = np.random.default_rng(0)
    gt = read_poses(shared_path("kitti_gt_poses", "07.txt")).poses[:300]
    R = axis_angle_to_rot(rng.normal(size=3) * 0.3)
    est = apply_sim3(gt, R, np.array([5.0, -2.0, 1.0]), 0.37)
    est = relative(est[0], est)
    g = Trajectory.from_poses(gt)
    assert evaluate(g, Trajectory.from_poses(est), align="7dof").ate < 1e-6
    assert evaluate(g, Trajectory.from_poses(est), align="6dof").ate > 1.0
    res = evaluate(g, Trajectory.from_poses(est), align="scale")
    assert res.scale == pytest.approx(1 / 0.37, rel=1e-6)


def test_scaled_real_gt_has_the_hand_computed_ate():
    """Positions scaled by 1.01 about the start: ATE (no alignment) is 1 % of the RMS distance
    from the start, computed here from the GT alone; no rotation error at all."""
    gt = read_poses(shared_path("kitti_gt_poses", "05.txt"))
    est = gt.poses.copy()
    est[:, :3, 3] = gt.poses[0, :3, 3] + 1.01 * (gt.poses[:, :3, 3] - gt.poses[0, :3, 3])
    res = evaluate(gt, Trajectory.from_poses(est))
    d = gt.poses[:, :3, 3] - gt.poses[0, :3, 3]
    assert res.ate == pytest.approx(0.01 * np.sqrt((d ** 2).sum(1).mean()), rel=1e-6)
    assert res.r_rel == pytest.approx(0.0, abs=1e-6) and 0.5 < res.t_rel <= 1.0 + 1e-9  # 1 % on straight segments


@pytest.mark.parametrize("seq, start", [("00", 300), ("04", 57), ("09", 1000)])
def test_estimate_starting_late_is_anchored_at_its_first_frame(seq, start):
    """A run over frames start..N-1 (13-column file: frame index first) starts at identity; its
    relative translations are 2 % long. Only the segments from GT frames start, start+10, ... can
    be scored, each with error 0.02 * chord / length (by hand below); the ATE is 2 % of the
    distance from the first frame, RMS."""
    gt = read_poses(shared_path("kitti_gt_poses", f"{seq}.txt")).poses
    rel = np.linalg.inv(gt[start]) @ gt[start:]
    est = rel.copy()
    est[:, :3, 3] *= 1.02
    traj = Trajectory(est, np.arange(start, len(gt)))
    res = evaluate(Trajectory.from_poses(gt), traj)
    dist = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))])
    errs = []
    for first in range(0, len(gt), 10):
        for L in (100, 200, 300, 400, 500, 600, 700, 800):
            beyond = np.nonzero(dist > dist[first] + L)[0]
            if first >= start and len(beyond):
                chord = np.linalg.inv(gt[first]) @ gt[beyond[0]]
                errs.append(0.02 * np.linalg.norm(chord[:3, 3]) / L)
    assert res.segments == len(errs) > 0
    assert res.t_rel == pytest.approx(np.mean(errs) * 100, rel=1e-5)
    assert res.r_rel == pytest.approx(0.0, abs=1e-6)
    assert res.path_length_m == pytest.approx(dist[-1] - dist[start], rel=1e-6)  # the stretch it covers
    d = rel[:, :3, 3]
    assert res.ate == pytest.approx(0.02 * np.sqrt((d ** 2).sum(1).mean()), rel=1e-5)


def test_real_gt_with_scaled_translation():
    """Scaling every position by 1.02: a segment's error is 0.02 * chord / length (reference below)."""
    gt = read_poses(shared_path("kitti_gt_poses", "04.txt")).poses
    est = gt.copy()
    est[:, :3, 3] *= 1.02
    res = evaluate(Trajectory.from_poses(gt), Trajectory.from_poses(est))
    # independent reference: path length in float64, plain loops
    dist = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1))])
    errs = []
    for first in range(0, len(gt), 10):
        for L in (100, 200, 300, 400, 500, 600, 700, 800):
            beyond = np.nonzero(dist > dist[first] + L)[0]
            if len(beyond):
                last = beyond[0]
                chord = np.linalg.inv(gt[first]) @ gt[last]
                errs.append(0.02 * np.linalg.norm(chord[:3, 3]) / L)
    assert res.segments == len(errs)
    assert res.t_rel == pytest.approx(np.mean(errs) * 100, rel=1e-5)


@pytest.mark.parametrize(
    "gt, est, t_rel, r_rel",
    [
        # DF-VO on 09 / 10 as published (D3LVO paper Table I, row DFVO)
        ("09", "dfvo/09.txt", 2.61, 0.29),
        ("10", "dfvo/10.txt", 2.29, 0.37),
        # ORB-SLAM2 stereo on 00 as published (Mur-Artal & Tardos 2017, Table II: 0.70 %, 0.25 deg/100 m)
        ("00", "00_orbslam2_stereo.txt", 0.70, 0.25),
    ],
)
def test_reproduces_published_numbers(gt, est, t_rel, r_rel):
    rep = evaluate_files([(shared_path("kitti_gt_poses", f"{gt}.txt"), shared_path("kitti_results", est))])
    s = rep.sequences[0]
    assert abs(s.t_rel - t_rel) <= 0.005 + 1e-9
    assert abs(s.r_rel - r_rel) <= 0.005 + 1e-9


def test_several_sequences_pool_segments():
    pairs = [(shared_path("kitti_gt_poses", f"{s}.txt"), shared_path("kitti_results", "dfvo", f"{s}.txt")) for s in ("09", "10")]
    rep = evaluate_files(pairs)
    a, b = rep.sequences
    o = rep.overall
    assert o["segments"] == a.segments + b.segments
    expect = (a.t_rel * a.segments + b.t_rel * b.segments) / (a.segments + b.segments)
    assert o["t_rel"] == pytest.approx(expect, rel=1e-5)
    assert min(a.t_rel, b.t_rel) < o["t_rel"] < max(a.t_rel, b.t_rel)
    # ATE is an RMSE: pooled over every frame of both, from the position errors by hand
    err = [np.linalg.norm(s.gt_poses[:, :3, 3] - s.est_poses[:, :3, 3], axis=1) for s in (a, b)]
    assert o["ate"] == pytest.approx(float(np.sqrt(np.mean(np.concatenate(err) ** 2))), rel=1e-6)


@pytest.mark.parametrize("seq, t_rel, r_rel, ate, rpe_t", [
    # kitti-odom-eval's own printout for this file (its result/example_0, README's misc/run_eg.jpeg,
    # `python eval_odom.py --result result/example_0/ --align 7dof`)
    ("09", 2.884112511407129, 0.24905618674615418, 8.38661922878607, 0.34341307706920193),
    ("10", 3.297839536933298, 0.3045899519453301, 6.630158107185018, 0.04735256371856307),
])
def test_skipped_frames_reproduce_the_published_7dof_numbers(seq, t_rel, r_rel, ate, rpe_t):
    gt = read_poses(shared_path("kitti_gt_poses", f"{seq}.txt"))
    est = read_poses(shared_path("kitti_results", "mono_example", f"{seq}.txt"))
    full = evaluate(gt, Trajectory(gt.poses.copy(), gt.frame_ids))
    res = evaluate(gt, est, align="7dof")
    assert 0 < res.segments < full.segments
    assert any("skips" in n for n in res.notes)
    assert res.t_rel == pytest.approx(t_rel, abs=5e-4) and res.r_rel == pytest.approx(r_rel, abs=5e-4)
    assert res.ate == pytest.approx(ate, abs=5e-4) and res.rpe_t == pytest.approx(rpe_t, abs=5e-4)


def test_short_path_reports_unavailable_but_computes_ate():
    gt = straight(50)  # 49 m
    est = straight(50, 1.1)
    res = evaluate(Trajectory.from_poses(gt), Trajectory.from_poses(est))
    assert res.t_rel is None and res.r_rel is None
    assert any("shorter than" in n for n in res.notes)
    assert res.ate == pytest.approx(np.sqrt(np.mean((0.1 * np.arange(50)) ** 2)))


def test_bad_inputs():
    gt = Trajectory.from_poses(straight(20))
    with pytest.raises(D3LVOInputError, match="only 20"):
        evaluate(gt, Trajectory.from_poses(straight(25)), est_name="est.txt")
    with pytest.raises(D3LVOInputError, match="at least 2"):
        evaluate(gt, Trajectory.from_poses(straight(1)))
    res = evaluate(gt, Trajectory.from_poses(straight(12)))
    assert any("12 of 20" in n for n in res.notes)
    with pytest.raises(D3LVOInputError, match="gt.txt: need at least 2"):
        evaluate(Trajectory.from_poses(straight(1)), Trajectory.from_poses(straight(2)), gt_name="gt.txt",
                 est_name="est.txt")
    with pytest.raises(D3LVOInputError, match="frame index -1 is negative"):
        evaluate(gt, Trajectory(straight(3), np.array([-1, 0, 1])))


def test_timed_poses_pair_by_time_and_numbered_ones_by_number():
    """By hand on a 1 m/frame straight drive at 10 Hz (ATE 0 when every pose lands on its own GT
    frame): a TUM estimate of every second frame pairs by its stamps, not its order; one whose
    stamps run past the ground truth's end is scored on the poses it has a pose for (a note counts
    the rest), and one on another clock altogether pairs by order, with a note. A 13-column ground truth of the even frames 0..98 pairs with
    an estimate numbered the same way; a frame it lacks is named."""
    times = np.arange(50) * 0.1
    gt = Trajectory(straight(50), np.arange(50), times)
    every_second = Trajectory(straight(50)[::2], np.arange(25), times[::2])
    res = evaluate(gt, every_second)
    assert res.ate == pytest.approx(0.0, abs=1e-12)
    assert any("skips 25 frames" in n for n in res.notes)
    late = Trajectory(straight(50)[::2], np.arange(25), times[::2] + 3.0)  # from frame 30 on, past the GT's end
    res = evaluate(gt, late, est_name="est.txt")  # the 10 poses at 3.0-4.8 s pair with GT frames 30-48
    assert any("15 of 25 poses have no ground-truth pose within 0.05 s: left out" in n for n in res.notes)
    assert res.frames == 10
    other_clock = Trajectory(straight(20), np.arange(20), times[:20] + 1e9)  # epoch stamps against 0-based ones
    res = evaluate(gt, other_clock)
    assert res.ate == pytest.approx(0.0, abs=1e-12) and any("paired by order" in n for n in res.notes)
    numbered = Trajectory(straight(50), np.arange(0, 100, 2), numbered=True)
    res = evaluate(numbered, Trajectory(straight(50)[::5], np.arange(0, 100, 10), numbered=True))
    assert res.ate == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(D3LVOInputError, match="frame 3 is not among the ground truth's numbered frames"):
        evaluate(numbered, Trajectory(straight(2), np.array([0, 3]), numbered=True))
    # an estimate that does not number its frames pairs with them by order
    assert evaluate(numbered, Trajectory.from_poses(straight(50))).ate == pytest.approx(0.0, abs=1e-12)
    # a lower-rate TUM estimate has no poses on adjacent GT frames: RPE unavailable (JSON null), said so
    res = evaluate(gt, Trajectory(straight(50)[::3], np.arange(17), times[::3]))
    assert res.to_dict()["rpe_t"] is None and any("RPE unavailable" in n for n in res.notes)
