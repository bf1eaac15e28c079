"""The no-learning direct tracker (the network's reference): hand-built geometry it must solve
exactly, the renderer's motion, and the CLI."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from d3lvo_deploy.calib import Calib
from d3lvo_deploy.direct import DirectConfig, DirectOdometry, huber_weights, pyramid
from d3lvo_deploy.geometry import axis_angle_to_rot, make_se3, relatives, rotation_angle, se3_inv
from d3lvo_deploy.points import in_depth_range
from d3lvo_deploy.poses import read_poses
from d3lvo_deploy.sequence import KittiSequence


def test_pyramid_levels_sit_on_even_source_pixels():
    """pyrDown keeps a ramp u + 10 v a ramp; level-1 pixel (i, j) is source pixel (2i, 2j), and
    the level's intrinsics say the same: a point projecting to source pixel (2j, 2i) projects to (j, i)."""
    v, u = np.mgrid[0:64, 0:96].astype(np.float32)
    K = np.array([[100.0, 0, 40.0], [0, 90.0, 30.0], [0, 0, 1]])
    lv = pyramid(u + 10 * v, K, 2)[1]
    i, j = 11, 17
    assert abs(lv.stack[i, j, 0] - (2 * j + 20 * i)) < 1e-3
    assert abs(lv.stack[i, j, 1] - 2.0) < 1e-3 and abs(lv.stack[i, j, 2] - 20.0) < 1e-3  # per level pixel
    X = np.array([(2 * j - 40.0) / 100.0 * 5, (2 * i - 30.0) / 90.0 * 5, 5.0])
    uv = lv.K @ X
    assert np.allclose(uv[:2] / uv[2], [j, i])


def test_depth_range_keeps_what_a_plain_float64_transform_keeps():
    """The float32 pre-filter must not drop or add a point, even within a micrometre of the limits."""
    rng = np.random.default_rng(3)
    T = make_se3(axis_angle_to_rot(np.array([1.2, -1.2, 1.2]) * 0.9), np.array([0.06, -0.08, -0.27]))
    cam = np.c_[rng.uniform(-30, 30, (4000, 2)), rng.uniform(-130, 130, 4000)]
    cam[:200, 2] = 0.5 + rng.choice([-1e-6, 1e-6], 200)  # at min_depth
    cam[200:400, 2] = 120.0 + rng.choice([-1e-6, 1e-6], 200)  # at max_depth
    velo = (cam - T[:3, 3]) @ T[:3, :3]  # the LiDAR points that T maps onto cam
    scan = np.c_[velo, rng.uniform(0, 1, 4000)].astype(np.float32)
    X = scan[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    expected = X[(X[:, 2] > 0.5) & (X[:, 2] < 120.0)]
    got = in_depth_range(scan, T, 0.5, 120.0)
    assert 100 < ((np.abs(got[:, 2] - 0.5) < 1e-4) | (np.abs(got[:, 2] - 120.0) < 1e-4)).sum() < 400
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)


def test_huber_threshold_follows_the_residual_scale():
    """Residuals 1..9 (median 5): threshold 1.345 * 1.4826 * 5 = 9.97, so all weigh 1; times 100
    the same; with an outlier at 1000 the median is 5.5 and the outlier gets 10.97 / 1000."""
    r = np.arange(1.0, 10.0)
    assert np.allclose(huber_weights(r), 1.0) and np.allclose(huber_weights(100 * r), 1.0)
    w = huber_weights(np.append(r, 1000.0))
    k = 1.345 * 1.4826 * 5.5
    assert np.allclose(w[:-1], 1.0) and abs(w[-1] - k / 1000.0) < 1e-9


def _texture(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A grey texture on the plane (coordinates in metres), values in [0.1, 0.9]: slow waves the
    coarse levels lock on, and 0.3-0.6 m ones (15-40 pixels) with gradients past the threshold."""
    return (0.5 + 0.12 * np.sin(1.3 * a + 0.4) * np.cos(0.9 * b) + 0.1 * np.sin(3.1 * a - 2.1 * b)
            + 0.09 * np.sin(17.0 * a + 9.0 * b) + 0.09 * np.cos(11.0 * a - 19.0 * b))


def _plane_scene(A: np.ndarray):
    """A tilted textured plane 6-12 m ahead, seen by a KITTI-like rig (image_2 with a baseline,
    LiDAR axes x forward / z up) before and after the image_2 motion A (frame 1 in frame 0)."""
    w, h = 640, 240
    K = np.array([[500.0, 0, 320.0], [0, 500.0, 120.0], [0, 0, 1]])
    P2 = K @ np.hstack([np.eye(3), [[0.06], [0.0], [0.0]]])  # image_2 centre 6 cm left of cam0
    R_cam_velo = np.array([[0, -1.0, 0], [0, 0, -1.0], [1.0, 0, 0]])
    calib = Calib(P2=P2, Tr=make_se3(R_cam_velo, [0.0, -0.08, -0.27]))
    n = np.array([0.3, -0.2, 1.0])
    n /= np.linalg.norm(n)
    d0 = 8.0  # plane n . X = d0 in frame 0's image_2 coordinates
    e1 = np.cross(n, [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)

    def render(T: np.ndarray) -> np.ndarray:
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ T[:3, :3].T
        s = (d0 - n @ T[:3, 3]) / (rays @ n)
        X = T[:3, 3] + s[..., None] * rays
        g = _texture(X @ e1, X @ e2)
        return np.repeat(np.round(255 * g).astype(np.uint8)[..., None], 3, 2)

    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [w - 1, h - 1], (30000, 2))
    rays = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], 1)
    X2 = rays * (d0 / (rays @ n))[:, None]
    velo = np.hstack([X2, np.ones((len(X2), 1))]) @ se3_inv(calib.T_cam2_velo).T
    scan = np.hstack([velo[:, :3], np.zeros((len(X2), 1))]).astype(np.float32)
    return calib, render(np.eye(4)), render(A), scan


def test_recovers_a_known_motion_on_a_textured_plane():
    """1.8 deg of rotation and 0.9 m of translation between two renders of a hand-built plane,
    from a zero-motion start: recovered within 1 mm and 0.005 deg, in image_2 and, through the
    rig's baseline, in cam0."""
    A = make_se3(axis_angle_to_rot([0.01, -0.03, 0.005]), [0.1, -0.05, 0.9])
    calib, img0, img1, scan = _plane_scene(A)
    odo = DirectOdometry(calib)
    odo.step(img0, scan)
    pose = odo.step(img1, None)
    est = odo.motion2
    t_err = np.linalg.norm(est[:3, 3] - A[:3, 3])
    r_err = np.degrees(rotation_angle(est[:3, :3].T @ A[:3, :3]))
    print(f"translation error {t_err * 1000:.3f} mm, rotation error {r_err:.5f} deg")
    assert t_err < 1e-3 and r_err < 0.005
    # cam0 moves by T_cam0_cam2 A T_cam2_cam0: with the 6 cm baseline the translation differs by R b - b
    b = np.array([0.06, 0.0, 0.0])
    expect_t = A[:3, :3] @ b + A[:3, 3] - b
    assert np.linalg.norm(pose[:3, 3] - expect_t) < 1e-3


def test_no_texture_no_points():
    """A flat grey image has no gradient: no point is kept and the tracker reports no motion
    instead of an arbitrary one."""
    A = make_se3(np.eye(3), [0.0, 0.0, 0.5])
    calib, _, _, scan = _plane_scene(A)
    flat = np.full((240, 640, 3), 128, np.uint8)
    odo = DirectOdometry(calib)
    odo.step(flat, scan)
    assert len(odo._prev.points) == 0
    assert np.allclose(odo.step(flat, scan), np.eye(4))


def test_config_must_name_iterations_per_level():
    with pytest.raises(ValueError, match="3 levels but 2 iteration counts"):
        DirectOdometry(_plane_scene(np.eye(4))[0], DirectConfig(iterations=(15, 15)))


def test_direct_tracker_follows_the_rendered_motion(small_synth):
    seq = KittiSequence.open(small_synth)
    odo = DirectOdometry(seq.calib)
    est = np.stack([odo.step(seq.image(i), seq.scan(i)) for i in range(len(seq))])
    gt_rel = relatives(seq.ground_truth.poses)
    err = relatives(est)
    t_err = np.linalg.norm(err[:, :3, 3] - gt_rel[:, :3, 3], axis=1)
    r_err = np.degrees(rotation_angle(np.swapaxes(err[:, :3, :3], 1, 2) @ gt_rel[:, :3, :3]))
    no_motion_t = np.linalg.norm(gt_rel[:, :3, 3], axis=1)
    print("per-pair translation error (m)", t_err.round(4), "no motion", no_motion_t.round(3))
    print("per-pair rotation error (deg)", r_err.round(4))
    assert np.all(t_err < 0.03 * no_motion_t)  # within 3 % of the motion itself
    assert np.all(r_err < 0.05)


def test_cli_run_method_direct_scores(small_synth, tmp_path):
    r = CliRunner().invoke(app, ["run", "--seq-dir", str(small_synth), "--method", "direct", "--out", str(tmp_path / "d.txt")])
    assert r.exit_code == 0, r.output
    assert len(read_poses(tmp_path / "d.txt")) == 6 and "RPE" in r.output
    r = CliRunner().invoke(app, ["run", "--seq-dir", str(small_synth), "--method", "orb", "--out", str(tmp_path / "e.txt")])
    assert r.exit_code == 1 and "--method must be d3lvo or direct" in r.output


def _kiss_icp_cam0(seq: KittiSequence) -> np.ndarray:
    """KISS-ICP's poses (`d3lvo_deploy.lidar_reference`) moved into cam0: the independent
    reference for real frames."""
    pytest.importorskip("kiss_icp.kiss_icp")
    from d3lvo_deploy.lidar_reference import kiss_icp_cam0

    return kiss_icp_cam0(seq)


def test_real_frames_end_near_lidar_odometry():
    """On the 20 real frames (traffic moving around the car), the direct tracker ends within 0.4 m
    of LiDAR-only KISS-ICP and its path is within 10 % of KISS-ICP's; standing still would be 4 m off."""
    from conftest import shared_path

    seq = KittiSequence.open(shared_path("kitti_raw_snippet", "sequences", "r0926"))
    ref = _kiss_icp_cam0(seq)
    odo = DirectOdometry(seq.calib)
    est = np.stack([odo.step(seq.image(i), seq.scan(i)) for i in range(len(seq))])
    length = lambda P: float(np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1).sum())  # noqa: E731
    end_off = float(np.linalg.norm(est[-1, :3, 3] - ref[-1, :3, 3]))
    print(f"KISS-ICP end {ref[-1, :3, 3].round(3)} path {length(ref):.2f} m; direct end {est[-1, :3, 3].round(3)} "
          f"path {length(est):.2f} m, {end_off:.2f} m off; no motion {np.linalg.norm(ref[-1, :3, 3]):.2f} m off")
    assert length(ref) > 3.0  # the reference itself moved
    assert end_off < 0.4 and abs(length(est) / length(ref) - 1) < 0.1


def _gate_case():
    """Frame t-1's points and frame t's LiDAR depth, the camera 1 m forward: a static point (the
    scan sees it at 9 m), a car that kept its distance (10 m where 9 m is expected: error 1/9), a
    point with no return at its pixel, and one hidden by something at 5 m (error 4/9)."""
    from d3lvo_deploy.direct import TrackedFrame

    K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])
    points = np.array([[0.0, 0.0, 10.0], [1.0, 0.0, 10.0], [0.0, 1.0, 20.0], [0.0, -1.0, 10.0]])
    depth = np.zeros((100, 100))
    depth[50, 50], depth[50, 61], depth[39, 50] = 9.0, 10.0, 5.0  # pixels (50, 50), (61.1, 50), (50, 38.9)
    forward = make_se3(np.eye(3), [0.0, 0.0, 1.0])
    return TrackedFrame.of(np.zeros((100, 100), np.float32), points, K, 1), depth, forward


def test_scan_gate_drops_what_moved():
    """The errors are the hand-computed ones; the gate drops the points above its limit and keeps a
    point without a return; at rest the static point's own error is 1/10."""
    from d3lvo_deploy.direct import depth_errors, scan_gated

    prev, depth, forward = _gate_case()
    K = prev.levels[0].K
    e = depth_errors(prev.points, forward, depth, K)
    assert np.isnan(e[2]) and e[[0, 1, 3]] == pytest.approx([0.0, 1 / 9, 4 / 9])
    assert scan_gated(prev, depth, forward, 0.05).points.tolist() == prev.points[[0, 2]].tolist()
    assert scan_gated(prev, depth, forward, 0.2).points.tolist() == prev.points[[0, 1, 2]].tolist()
    assert scan_gated(prev, depth, forward, 0.5) is prev
    assert depth_errors(prev.points[:1], np.eye(4), depth, K)[0] == pytest.approx(0.1)  # 9 m seen, 10 m expected


def test_scan_gate_comes_from_the_model():
    """`--method direct` stands for a model's classical mode: its `pt_scan_gate` is the tracker's
    gate, and a frame then keeps its LiDAR depth (also without the restart's check)."""
    from d3lvo_deploy.bundled import bundled_model_dir
    from d3lvo_deploy.manifest import load_manifest

    model = dict(load_manifest(bundled_model_dir())["model_config"], pt_scan_gate=0.05, pt_restart_depth=0.0)
    cfg = DirectConfig.of_model(model)
    assert cfg.scan_gate == 0.05 and cfg.reads_scan and not cfg.checks_restart_on_scan
    assert not DirectConfig().reads_scan
