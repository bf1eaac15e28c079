"""The motion guard: hand-built motions whose speed change is or is not within a car's reach, and
both trackers keeping the previous motion where it is not (a resumed run as an uninterrupted one)."""

from __future__ import annotations

import numpy as np
import pytest

from d3lvo_deploy import direct
from d3lvo_deploy.direct import DirectOdometry
from d3lvo_deploy.geometry import axis_angle_to_rot, make_se3, relatives, rotation_angle
from d3lvo_deploy.motion_guard import CHOSEN_MAX_ACCEL, MotionGuard, guard_motion, scaled_motion
from d3lvo_deploy.sequence import KittiSequence


def forward(metres: float, yaw_deg: float = 0.0) -> np.ndarray:
    return make_se3(axis_angle_to_rot(np.array([0.0, np.radians(yaw_deg), 0.0])), [0.0, 0.0, metres])


def test_a_step_out_of_a_cars_reach_keeps_the_previous_motion():
    g = MotionGuard(max_accel=30.0)
    assert not MotionGuard().enabled  # off unless asked for
    last = forward(1.0, 1.0)  # 10 m/s over 0.1 s
    # 0.2 m in 0.1 s: 2 m/s, a change of 8 m/s in 0.1 s (80 m/s^2): replaced by the last motion
    kept, held = guard_motion(forward(0.2), 0.1, last, 0.1, g)
    assert held and np.allclose(kept, last)
    # 0.75 m: 2.5 m/s less in 0.1 s (25 m/s^2, within 30): kept as solved
    step = forward(0.75, -0.5)
    kept, held = guard_motion(step, 0.1, last, 0.1, g)
    assert not held and kept is step
    # faster by 3.5 m/s: as out of reach as slower
    assert guard_motion(forward(1.35), 0.1, last, 0.1, g)[1]
    # no motion before it (a run's first pair), or the guard off: whatever was solved
    assert not guard_motion(forward(0.2), 0.1, None, 0.1, g)[1]
    assert not guard_motion(forward(0.2), 0.1, last, 0.1, MotionGuard(max_accel=0.0))[1]


def test_the_guard_reads_speeds_so_a_dropped_frame_is_no_jump():
    g = MotionGuard(max_accel=30.0)
    last = forward(1.0, 1.0)
    # a frame dropped: twice the step in twice the time is the same speed
    assert not guard_motion(forward(2.0, 2.0), 0.2, last, 0.1, g)[1]
    # held over 0.2 s: the last motion at constant velocity, twice its translation and its angle
    kept, held = guard_motion(forward(0.4), 0.2, last, 0.1, g)
    assert held
    assert np.allclose(kept[:3, 3], [0.0, 0.0, 2.0])
    assert np.degrees(rotation_angle(kept[:3, :3])) == pytest.approx(2.0)
    assert np.allclose(scaled_motion(last, 1.0), last)


def test_interval_comes_from_stamps_else_the_period():
    g = MotionGuard(period=0.05)
    assert g.interval(1.0, 1.1) == pytest.approx(0.1)
    assert g.interval(None, 1.1) == 0.05 and g.interval(1.1, 1.1) == 0.05


def _fake_track(steps: list[float]):
    """`direct.track` replaced by hand-made motions, one per pair in order: the guard is tested, not
    the solve."""
    queue = list(steps)

    def track(prev, cur, start, cfg):
        return forward(queue.pop(0))

    return track


def test_direct_tracker_keeps_the_previous_motion_where_the_solve_jumps(small_synth, monkeypatch):
    seq = KittiSequence.open(small_synth)
    # the first pair comes from the cold start's solves (not faked); the second solves 1.0 m, the
    # third 0.1 m (9 m/s slower in 0.1 s), the fourth 1.05 m
    monkeypatch.setattr(direct, "first_motion", lambda prev, cur, cfg: forward(0.9))
    monkeypatch.setattr(direct, "track", _fake_track([1.0, 0.1, 1.05, 1.0]))
    odo = DirectOdometry(seq.calib, guard=MotionGuard(CHOSEN_MAX_ACCEL))
    poses = np.stack([odo.step(seq.image(i), seq.scan(i), float(seq.times[i])) for i in range(5)])
    steps = np.linalg.norm(relatives(poses)[:, :3, 3], axis=1)  # cam0 steps: the same length as image_2's
    assert steps == pytest.approx([0.9, 1.0, 1.0, 1.05], abs=1e-9)
    assert odo.guarded == 1
    # off (the default), the solve as it came
    monkeypatch.setattr(direct, "track", _fake_track([1.0, 0.1, 1.05, 1.0]))
    odo = DirectOdometry(seq.calib)
    poses = np.stack([odo.step(seq.image(i), seq.scan(i), float(seq.times[i])) for i in range(5)])
    assert np.linalg.norm(relatives(poses)[:, :3, 3], axis=1) == pytest.approx([0.9, 1.0, 0.1, 1.05], abs=1e-9)
    assert odo.guarded == 0


def test_a_resumed_direct_run_guards_as_an_uninterrupted_one(small_synth, monkeypatch):
    """Primed with two poses, the tracker compares the next pair with their motion, as it would
    have had it run through."""
    seq = KittiSequence.open(small_synth)
    monkeypatch.setattr(direct, "first_motion", lambda prev, cur, cfg: forward(0.9))
    monkeypatch.setattr(direct, "track", _fake_track([1.0, 0.1]))
    whole = DirectOdometry(seq.calib, guard=MotionGuard(CHOSEN_MAX_ACCEL))
    poses = [whole.step(seq.image(i), seq.scan(i), float(seq.times[i])) for i in range(4)]
    monkeypatch.setattr(direct, "track", _fake_track([0.1]))
    resumed = DirectOdometry(seq.calib, guard=MotionGuard(CHOSEN_MAX_ACCEL))
    resumed.prime(seq.image(2), seq.scan(2), poses[2], poses[1], stamp=float(seq.times[2]),
                  previous_stamp=float(seq.times[1]))
    assert np.allclose(resumed.step(seq.image(3), seq.scan(3), float(seq.times[3])), poses[3])
    assert resumed.guarded == 1


def test_network_run_keeps_the_previous_motion_and_starts_the_next_pair_from_it(small_synth):
    """The bundled model's pose outputs replaced by hand-made motions (in image_2, as the graph
    gives them): the pair that jumps is replaced by the one before, and the next pair starts there
    rather than at the graph's own start."""
    from d3lvo_deploy.bundled import bundled_model_dir
    from d3lvo_deploy.odometry import Odometry

    seq = KittiSequence.open(small_synth)
    odo = Odometry(bundled_model_dir(), seq.calib, guard=MotionGuard(CHOSEN_MAX_ACCEL))
    solved = [forward(1.0), forward(0.1), forward(1.05)]
    starts = []

    def flow_pose(prev, cur, camera):
        starts.append(camera["init_pose"][0].astype(np.float64))
        A = solved[len(starts) - 1]
        return {"matrix": A[None].astype(np.float32), "start_next": forward(0.5)[None].astype(np.float32)}

    odo.model.flow_pose = flow_pose
    poses = np.stack([odo.step(seq.image(i), seq.scan(i), float(seq.times[i])) for i in range(4)])
    assert np.linalg.norm(relatives(poses)[:, :3, 3], axis=1) == pytest.approx([1.0, 1.0, 1.05], abs=1e-5)
    assert odo.guarded == 1
    # pairs 2 and 3 started from the graph's start, then from the motion the guard kept
    assert np.allclose(starts[1][:3, 3], [0, 0, 0.5], atol=1e-6) and np.allclose(starts[2][:3, 3], [0, 0, 1.0], atol=1e-6)

    # resumed after frame 1 (its pose and the one before, their stamps), the jump is caught alike
    resumed = Odometry(bundled_model_dir(), seq.calib, guard=MotionGuard(CHOSEN_MAX_ACCEL))
    resumed.model.flow_pose = flow_pose
    del starts[:]
    solved[:] = [forward(0.1)]
    resumed.prime(seq.image(1), seq.scan(1), poses[1], poses[0], stamp=float(seq.times[1]),
                  previous_stamp=float(seq.times[0]))
    assert np.allclose(resumed.step(seq.image(2), seq.scan(2), float(seq.times[2])), poses[2], atol=1e-5)
    assert resumed.guarded == 1


def test_cli_takes_the_limit_records_it_and_refuses_a_negative_one(small_synth, tmp_path):
    from typer.testing import CliRunner

    from cli.main import app
    from d3lvo_deploy.results import read_config

    r = CliRunner().invoke(app, ["run", str(small_synth), "--method", "direct", "--max-accel", "-1",
                                 "--out", str(tmp_path / "a.txt")])
    assert r.exit_code == 1 and "--max-accel must be 0 (off) or a positive number" in r.output
    r = CliRunner().invoke(app, ["run", str(small_synth), "--method", "direct", "--max-accel", "30",
                                 "--out-dir", str(tmp_path / "run")])
    assert r.exit_code == 0, r.output
    assert read_config(tmp_path / "run")["max_accel"] == 30.0


def test_resume_continues_only_a_run_with_the_same_guard(small_synth, tmp_path):
    """The guard changes the poses, so --resume refuses to continue a run made with another limit; a
    record written without the setting is a run without the guard."""
    from typer.testing import CliRunner

    from cli.main import app

    out = tmp_path / "d.txt"
    run = lambda *extra: CliRunner().invoke(app, ["run", str(small_synth), "--method", "direct", "--out", str(out),  # noqa: E731
                                                  *extra])
    assert run("--max-accel", "30").exit_code == 0
    lines = out.read_text().splitlines(keepends=True)
    out.write_text("".join(lines[:3]))  # an interrupted run
    r = run("--resume")
    assert r.exit_code == 1 and "max_accel = 30.0, this one has 0.0" in r.output
    assert run("--resume", "--max-accel", "30").exit_code == 0
    # the classical tracker's resumed start comes from the poses as written (docs/runtime.md)
    assert np.allclose(np.loadtxt(out), np.loadtxt(lines), atol=1e-6)
    record = out.with_name(out.name + ".config.toml")
    record.write_text("".join(l for l in record.read_text().splitlines(keepends=True) if not l.startswith("max_accel")))
    out.write_text("".join(lines[:3]))
    assert run("--resume").exit_code == 0  # no max_accel recorded: a run without the guard


# frame times of the uneven clip: frame 2 comes 0.2 s after frame 1 (a frame dropped)
UNEVEN = [0.0, 0.1, 0.3, 0.4, 0.5, 0.6]
# the solve of the pair ending at each time (m forward), and what the guard at 30 m/s^2 keeps: 1.2 m
# in 0.2 s is 6 m/s, 4 m/s slower than 10 m/s, within 30 x 0.2 (kept); 0.1 m in 0.1 s after it is 5
# m/s slower, beyond 30 x 0.1 (the previous motion at constant velocity over 0.1 s: 0.6 m)
SOLVED = {0.1: 1.0, 0.3: 1.2, 0.4: 0.1, 0.5: 0.62, 0.6: 0.6}
KEPT = [1.0, 1.2, 0.6, 0.62, 0.6]


@pytest.fixture
def uneven_clip(small_synth, tmp_path):
    import shutil

    clip = tmp_path / "uneven"
    shutil.copytree(small_synth, clip)
    (clip / "times.txt").write_text("".join(f"{t:.6e}\n" for t in UNEVEN))
    (clip / "poses.txt").unlink()  # the rendered motion is not this clip's: no scoring
    return clip


def _steps(path) -> np.ndarray:
    from d3lvo_deploy.poses import read_poses

    return np.linalg.norm(relatives(read_poses(path).poses)[:, :3, 3], axis=1)


def _solves(monkeypatch, first_pair: int) -> list[float]:
    """`direct.track` answering the clip's pairs from `first_pair` on (1: the first after the cold
    start) with SOLVED; returns the list the starts it was given go to."""
    starts: list[float] = []

    def track(prev, cur, start, cfg):
        starts.append(float(np.linalg.norm(start[:3, 3])))
        return forward(list(SOLVED.values())[first_pair + len(starts) - 1])

    monkeypatch.setattr(direct, "first_motion", lambda prev, cur, cfg: forward(SOLVED[0.1]))
    monkeypatch.setattr(direct, "track", track)
    return starts


def test_run_reads_the_recordings_times(uneven_clip, tmp_path, monkeypatch):
    """`d3lvo run --method direct` passes each frame's time: the dropped frame's longer step is no
    jump, the later one is, and the next pair starts from the motion kept; resumed after two poses
    (the dropped frame's pair the first to solve) it writes the same."""
    from typer.testing import CliRunner

    from cli.main import app

    out = tmp_path / "d.txt"
    args = ["run", str(uneven_clip), "--method", "direct", "--max-accel", "30", "--out", str(out)]
    starts = _solves(monkeypatch, 1)
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    assert _steps(out) == pytest.approx(KEPT, abs=1e-9)
    # constant velocity over each pair's own time: 1 m in 0.1 s is 2 m over the dropped frame's
    # 0.2 s, 1.2 m in 0.2 s is 0.6 m over 0.1 s
    assert starts == pytest.approx([2.0, 0.6, 0.6, 0.62], abs=1e-9)
    assert "motion guard: the previous motion kept on 1 of 5 pairs" in r.output
    out.write_text("".join(out.read_text().splitlines(keepends=True)[:2]))
    _solves(monkeypatch, 1)
    r = CliRunner().invoke(app, args + ["--resume"])
    assert r.exit_code == 0, r.output
    assert _steps(out) == pytest.approx(KEPT, abs=1e-6)


@pytest.mark.parametrize("how", [[], ["--pipeline"], ["resume", 3], ["resume", 2]])
def test_network_run_reads_the_recordings_times(how, uneven_clip, tmp_path, monkeypatch):
    """The same through the network's run, one frame at a time, pipelined (onnxruntime: the next frame
    prepared and encoded on the reader thread), and resumed after three poses (the jump the first
    pair to solve) or two (the dropped frame's pair first: its time from both primed frames')."""
    from typer.testing import CliRunner

    from cli.main import app
    from d3lvo_deploy.onnx_model import StageModel

    starts = {}

    def flow_pose(self, prev, cur, camera):
        starts[round(cur["stamp"], 6)] = float(np.linalg.norm(camera["init_pose"][0, :3, 3]))
        A = forward(SOLVED[round(cur["stamp"], 6)])[None].astype(np.float32)
        return {"matrix": A, "start_next": A}

    monkeypatch.setattr(StageModel, "flow_pose", flow_pose)
    out = tmp_path / "n.txt"
    args = ["run", str(uneven_clip), "--backend", "onnxruntime", "--max-accel", "30", "--out", str(out)]
    r = CliRunner().invoke(app, args + [a for a in how if a == "--pipeline"])
    assert r.exit_code == 0, r.output
    if "resume" in how:
        out.write_text("".join(out.read_text().splitlines(keepends=True)[:how[1]]))
        r = CliRunner().invoke(app, args + ["--resume"])
        assert r.exit_code == 0, r.output
    assert _steps(out) == pytest.approx(KEPT, abs=1e-5)
    # each pair after the first started at constant velocity over its own time, as the classical
    # tracker's (the resumed run's from the saved start, over the primed frames' times)
    assert [starts[t] for t in (0.3, 0.4, 0.5, 0.6)] == pytest.approx([2.0, 0.6, 0.6, 0.62], abs=1e-5)


def test_prime_without_the_pose_before_forgets_the_motion(small_synth, monkeypatch):
    """A tracker primed with one pose has no motion to start from or to guard against, whatever it
    tracked before: its next pair starts cold (the cold start's solve), as a fresh run's first."""
    from d3lvo_deploy.bundled import bundled_model_dir
    from d3lvo_deploy.odometry import Odometry

    seq = KittiSequence.open(small_synth)
    monkeypatch.setattr(direct, "first_motion", lambda prev, cur, cfg: forward(0.9))
    monkeypatch.setattr(direct, "track", lambda prev, cur, start, cfg: forward(0.2))
    classical = DirectOdometry(seq.calib, guard=MotionGuard(CHOSEN_MAX_ACCEL))
    network = Odometry(bundled_model_dir(), seq.calib, guard=MotionGuard(CHOSEN_MAX_ACCEL))
    network.model.flow_pose = lambda prev, cur, camera: {"matrix": forward(1.0)[None].astype(np.float32)}
    for odo in (classical, network):
        odo.prime(seq.image(1), seq.scan(1), forward(1.0), np.eye(4))  # a motion of 1 m
        assert not odo.cold
        odo.prime(seq.image(2), seq.scan(2), forward(2.0))
        assert odo.cold and np.allclose(odo.motion2, np.eye(4))
    assert network.kept2 is None
    # the classical tracker's next pair: the cold start's 0.9 m, not a 0.2 m solve held at 1 m
    after = classical.step(seq.image(3), seq.scan(3), float(seq.times[3]))
    assert np.linalg.norm(after[:3, 3] - forward(2.0)[:3, 3]) == pytest.approx(0.9, abs=1e-9)
