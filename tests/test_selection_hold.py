"""The pose choice's memory (`pt_select_hold`): the weighted pose held on the pairs after each one
the graph keeps it on, in the runtime and through --resume (an exported graph that holds:
`scan_judge_model` in tests/test_point_solver.py and tests/test_runtime.py)."""

from __future__ import annotations

import numpy as np
import pytest

from d3lvo_deploy.bundled import bundled_model_dir
from d3lvo_deploy.geometry import accumulate, change_frame, make_se3
from d3lvo_deploy.odometry import Odometry
from d3lvo_deploy.onnx_model import StageModel
from d3lvo_deploy.pipeline import RunConfig, run_sequence, start_file
from d3lvo_deploy.poses import read_poses
from d3lvo_deploy.selection import SELECT_KEPT_OUTPUT, held_pose, hold_step
from d3lvo_deploy.sequence import KittiSequence
from models.config import D3LVOConfig


def test_hold_step_keeps_the_weighted_pose_on_the_pairs_after_each_kept_one():
    """Traced by hand with hold 2: a kept pair starts the count again, so kept pairs two apart
    hold on without a gap, and the count runs out two pairs after the last."""
    kept = [False, True, False, False, False, True, False, True, False, False, False]
    want = [False, True, True, True, False, True, True, True, True, True, False]
    left, used = 0, []
    for k in kept:
        use, left = hold_step(k, left, 2)
        used.append(use)
    assert used == want and left == 0
    assert [hold_step(k, 0, 0)[0] for k in kept] == kept  # hold 0: the graph's choice alone


def test_a_held_pair_takes_the_weighted_pose_only_where_it_is_finite():
    """`held_pose` on graph outputs: the weighted pose on a held pair, the kept `matrix` where the
    weighted pose is not finite (the count still runs down), `matrix` on a pair the graph kept."""
    out = lambda kept, weighted: {"matrix": CLASSICAL[None], "start_next": weighted[None],  # noqa: E731
                                  SELECT_KEPT_OUTPUT: np.array([float(kept)])}
    pose, left = held_pose(out(False, WEIGHTED), 2, 2)
    np.testing.assert_array_equal(pose, WEIGHTED)
    assert left == 1
    pose, left = held_pose(out(False, np.full((4, 4), np.nan)), 1, 2)
    np.testing.assert_array_equal(pose, CLASSICAL)
    assert left == 0
    pose, left = held_pose(out(True, WEIGHTED), 0, 2)
    np.testing.assert_array_equal(pose, CLASSICAL)  # the graph's own `matrix` where it kept the weighted pose
    assert left == 2


def test_a_hold_needs_a_choice_to_hold():
    with pytest.raises(ValueError, match="pt_select_hold needs"):
        D3LVOConfig(pose_head="points", pt_select_hold=2)
    with pytest.raises(ValueError, match="whole number"):
        D3LVOConfig(pose_head="points", pt_select=0.003, pt_select_hold=-1)


# the scripted graph: per pair (frame t = 1..5), whether it kept the weighted pose; with hold 2 the
# runtime keeps it on pairs 2, 3, 4 (frames t) and after each pair has hold_left 0 0 2 1 0 0 (frames 0..5)
KEPT = {1: False, 2: True, 3: False, 4: False, 5: False}
USED = {1: False, 2: True, 3: True, 4: True, 5: False}
LEFT = [0, 0, 2, 1, 0, 0]
CLASSICAL, WEIGHTED = make_se3(np.eye(3), [0.0, 0.0, 0.5]), make_se3(np.eye(3), [0.02, 0.0, 0.6])


def scripted(seq: KittiSequence, model: StageModel) -> Odometry:
    """The bundled model's tracker with hold 2 and a flow+pose stage that returns, for the pair
    ending at frame t (found by its stamp), the classical or weighted pose as the choice `KEPT`."""
    odo = Odometry(bundled_model_dir(), seq.calib, model=model)
    odo.hold = 2
    frame = {float(t): i for i, t in enumerate(seq.times)}

    def flow_pose(enc, beside=None):
        if beside is not None:
            beside.result()
        t = frame[float(enc["stamp"])]
        kept = KEPT[t]
        return {"matrix": (WEIGHTED if kept else CLASSICAL)[None].astype(np.float32),
                "start_next": WEIGHTED[None].astype(np.float32), SELECT_KEPT_OUTPUT: np.array([float(kept)], np.float32)}
    odo._flow_pose = flow_pose
    return odo


def expected_poses(seq: KittiSequence) -> np.ndarray:
    rel = [change_frame(WEIGHTED if USED[t] else CLASSICAL, seq.calib.T_cam0_cam2) for t in range(1, len(seq))]
    return accumulate(np.array(rel))


def test_the_runtime_holds_the_weighted_pose_and_a_resumed_run_holds_on(small_synth, tmp_path):
    """The poses follow the hand-traced choice; each line of the `.start` file ends with the count
    left, and a run stopped after frame 2 (the count at 2) and resumed writes what the
    uninterrupted run wrote: without the saved count frames 3 and 4 would take the classical pose."""
    seq = KittiSequence.open(small_synth)
    assert len(seq) == 6
    model = StageModel(bundled_model_dir())  # one set of sessions; each run's state is its tracker's
    full, part = tmp_path / "full.txt", tmp_path / "part.txt"
    run_sequence(seq, None, RunConfig(out=full), odometry=scripted(seq, model))
    np.testing.assert_allclose(read_poses(full).poses, expected_poses(seq), atol=1e-5)
    assert [int(r.split()[-1]) for r in start_file(full).read_text().splitlines()] == LEFT
    run_sequence(seq, None, RunConfig(out=part, end=3), odometry=scripted(seq, model))
    run_sequence(seq, None, RunConfig(out=part, resume=True), odometry=scripted(seq, model))
    assert part.read_text() == full.read_text()
    assert start_file(part).read_text() == start_file(full).read_text()
    # the weighted pose differs from the classical one by 0.1 m a pair: not holding would show
    unheld = accumulate(np.array([change_frame(WEIGHTED if KEPT[t] else CLASSICAL, seq.calib.T_cam0_cam2)
                                  for t in range(1, len(seq))]))
    assert np.abs(unheld[-1, :3, 3] - read_poses(full).poses[-1, :3, 3]).max() > 0.15
