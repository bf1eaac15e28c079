"""SE(3)/SO(3): hand-computed cases plus hypothesis property tests of round-trips and group laws."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from d3lvo_deploy import geometry as g

unit = st.floats(-1.0, 1.0, allow_nan=False)
quats = st.tuples(unit, unit, unit, unit).filter(lambda q: np.linalg.norm(q) > 0.1).map(np.array)
vec3 = st.tuples(*(st.floats(-50, 50, allow_nan=False),) * 3).map(np.array)
rvecs = st.tuples(*(st.floats(-3.0, 3.0, allow_nan=False),) * 3).map(np.array).filter(lambda v: np.linalg.norm(v) < 3.1)


def se3_from(q, t):
    return g.make_se3(g.quat_to_rot(q), t)


def test_quaternion_hand_cases():
    # 90 deg about z: x -> y
    s = np.sqrt(0.5)
    R = g.quat_to_rot([s, 0, 0, s])
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # 180 deg about x: w = 0, the branch where Shepperd's method must not divide by w
    np.testing.assert_allclose(g.rot_to_quat(np.diag([1.0, -1.0, -1.0])), [0, 1, 0, 0], atol=1e-12)
    # scalar-last (TUM) ordering
    np.testing.assert_allclose(g.quat_to_rot([0, 0, s, s], scalar_first=False), R, atol=1e-12)


@given(quats)
def test_quaternion_round_trip_and_sign(q):
    R = g.quat_to_rot(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(R) > 0
    np.testing.assert_allclose(g.quat_to_rot(-q), R, atol=1e-12)  # q and -q: same rotation
    back = g.rot_to_quat(R)
    assert back[0] >= 0
    qn = q / np.linalg.norm(q)
    assert min(np.abs(back - qn).max(), np.abs(back + qn).max()) < 1e-7  # w ~ 0: either sign is w >= 0
    if abs(qn[0]) > 1e-6:
        np.testing.assert_allclose(back, g.quat_canonical(q), atol=1e-7)


@given(rvecs)
def test_axis_angle_round_trip(r):
    R = g.axis_angle_to_rot(r)
    np.testing.assert_allclose(g.rot_to_axis_angle(R), r, atol=1e-7)
    np.testing.assert_allclose(g.rotation_angle(R), np.linalg.norm(r), atol=1e-6)


def test_axis_angle_matches_quaternion_hand_case():
    ang = 0.7
    np.testing.assert_allclose(g.axis_angle_to_rot([0, ang, 0]),
                               g.quat_to_rot([np.cos(ang / 2), 0, np.sin(ang / 2), 0]), atol=1e-12)


@settings(max_examples=50)
@given(quats, vec3, quats, vec3, quats, vec3)
def test_group_laws(q1, t1, q2, t2, q3, t3):
    A, B, C = se3_from(q1, t1), se3_from(q2, t2), se3_from(q3, t3)
    np.testing.assert_allclose(g.compose(g.compose(A, B), C), g.compose(A, g.compose(B, C)), atol=1e-8)
    np.testing.assert_allclose(A @ g.se3_inv(A), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(g.se3_inv(g.compose(A, B)), g.compose(g.se3_inv(B), g.se3_inv(A)), atol=1e-8)
    np.testing.assert_allclose(A @ g.relative(A, B), B, atol=1e-8)


@settings(max_examples=30)
@given(st.lists(st.tuples(quats, vec3), min_size=2, max_size=8))
def test_accumulate_inverts_relatives(items):
    poses = np.stack([se3_from(q, t) for q, t in items])
    poses = g.relative(poses[0], poses)
    np.testing.assert_allclose(g.accumulate(g.relatives(poses)), poses, atol=1e-7)


def test_change_frame_hand_case():
    # 90 deg yaw of a rig about cam0's centre, seen from a camera 6 cm to the side: t = b - R b
    b = np.array([0.06, 0.0, 0.0])
    T_b_a = g.make_se3(np.eye(3), b)
    A = g.make_se3(g.axis_angle_to_rot([0, np.pi / 2, 0]), np.zeros(3))
    out = g.change_frame(A, T_b_a)
    np.testing.assert_allclose(out[:3, 3], [0.06, 0.0, 0.06], atol=1e-12)
    np.testing.assert_allclose(out[:3, :3], A[:3, :3], atol=1e-12)


@settings(max_examples=30)
@given(quats, vec3, st.floats(0.2, 5.0))
def test_umeyama_recovers_similarity(q, t, s):
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3)) * 10
    R = g.quat_to_rot(q)
    dst = s * src @ R.T + t
    R7, t7, s7 = g.umeyama(src, dst, with_scale=True)
    np.testing.assert_allclose(R7, R, atol=1e-7)
    np.testing.assert_allclose(t7, t, atol=1e-6)
    assert abs(s7 - s) < 1e-8
    R6, t6, s6 = g.umeyama(src, src @ R.T + t, with_scale=False)
    assert s6 == 1.0
    np.testing.assert_allclose(R6, R, atol=1e-7)
