"""The network's point solver: the classical tracker with learned weights, checked against the numpy
tracker (written separately), cv2, hand-built geometry and its own ONNX export."""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
import onnx
import pytest

torch = pytest.importorskip("torch")

from d3lvo_deploy.cold_start import ColdStartConfig  # noqa: E402
from d3lvo_deploy import direct  # noqa: E402
from d3lvo_deploy.direct import DirectConfig, DirectOdometry, track  # noqa: E402
from d3lvo_deploy.geometry import (axis_angle_to_rot, make_se3, rotation_angle, rotation_angle_precise,  # noqa: E402
                                   se3_inv)
from d3lvo_deploy.points import (PointConfig, gradients, grey_image, pad_points, solver_pyramid,  # noqa: E402
                                 textured_points)
from d3lvo_deploy.sequence import KittiSequence  # noqa: E402
from models.gauss_newton import gauss_jordan, so3_exp_small  # noqa: E402
from models import gauss_newton as gn  # noqa: E402
from models.point_solver import (SolverSettings, consensus_gain, image_pyramids, lidar_depth_error, msac_gains,  # noqa: E402
                                 masked_median, project, pyr_down, rotations_differ, restore_explained, sample_at, solve, with_gradients)
from test_direct import _plane_scene  # noqa: E402

D = torch.float64


def _t(a) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(a), dtype=D)


def _k(K: np.ndarray) -> torch.Tensor:
    return _t([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]]])


def test_pyramid_and_gradients_are_cv2s():
    """pyr_down is cv2.pyrDown (reflect-101 borders, odd sizes round up); the gradient channels are
    the tracker's central differences with replicated edges."""
    img = np.random.default_rng(3).uniform(size=(37, 53)).astype(np.float32)
    ours = pyr_down(torch.from_numpy(img)[None, None])[0, 0].numpy()
    assert ours.shape == (19, 27) and np.abs(ours - cv2.pyrDown(img)).max() < 1e-6
    g = with_gradients(torch.from_numpy(img)[None, None])[0].numpy()
    gx, gy = gradients(img)
    assert np.abs(g[1] - gx).max() < 1e-6 and np.abs(g[2] - gy).max() < 1e-6


def test_runtime_pyramids_are_the_graphs():
    """The runtime's cv2 pyramids (the exported graph's inputs) are what the torch solver builds
    from the two grey images, level by level, on an odd-sized image."""
    rng = np.random.default_rng(5)
    img1, img2 = (rng.uniform(size=(45, 71)).astype(np.float32) for _ in range(2))
    grey1, stack2 = image_pyramids(torch.from_numpy(img1)[None, None], torch.from_numpy(img2)[None, None], 3)
    ours1, ours2 = solver_pyramid(img1, 3), solver_pyramid(img2, 3)
    assert [a.shape for a in ours2] == [(3, 45, 71), (3, 23, 36), (3, 12, 18)]
    for k in range(3):
        assert np.abs(ours1[k][:1] - grey1[k][0].numpy()).max() < 1e-6
        assert np.abs(ours2[k] - stack2[k][0].numpy()).max() < 1e-6


def test_small_ops_against_numpy():
    """Gauss-Jordan against numpy's LU solve; the series exponential against Rodrigues; the masked
    median against np.median (odd and even counts)."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(3, 6, 6))
    A = A @ A.transpose(0, 2, 1) + np.eye(6)
    b = rng.normal(size=(3, 6, 1))
    assert np.abs(gauss_jordan(torch.cat([_t(A), _t(b)], -1)).numpy() - np.linalg.solve(A, b)).max() < 1e-10
    w = np.array([[0.01, -0.02, 0.03]])
    assert np.abs(so3_exp_small(_t(w))[0].numpy() - axis_angle_to_rot(w[0])).max() < 1e-12
    a = rng.uniform(size=(2, 9))
    mask = np.ones((2, 9))
    mask[0, 4:] = 0  # 4 values: the mean of the middle two
    mask[1, 7:] = 0  # 7 values
    got = masked_median(_t(a), _t(mask))[:, 0].numpy()
    assert np.allclose(got, [np.median(a[0, :4]), np.median(a[1, :7])])


def _plane_inputs(A: np.ndarray, capacity: int = 8192):
    calib, img0, img1, scan = _plane_scene(A)
    grey0, grey1 = grey_image(img0), grey_image(img1)
    X = textured_points(scan, calib.T_cam2_velo, calib.K2, grey0, PointConfig(capacity=capacity))
    pts, mask = pad_points(X, len(X) + 500)  # a list longer than the points: padding must not count
    return calib, (img0, img1, scan), (_t(grey0)[None, None], _t(grey1)[None, None], _t(pts), _t(mask)), X


def test_recovers_a_known_motion_on_a_textured_plane():
    """The same hand-built plane as the numpy tracker's test, padded to a fixed list: the motion
    is recovered within 1 mm and 0.005 deg from a zero-motion start."""
    A = make_se3(axis_angle_to_rot([0.01, -0.03, 0.005]), [0.1, -0.05, 0.9])
    calib, _, (g0, g1, pts, mask), X = _plane_inputs(A)
    assert len(X) > 500
    est = solve(*image_pyramids(g0, g1, 3), pts, mask, _k(calib.K2), _t(np.eye(4))[None], SolverSettings())[-1][0].numpy()
    t_err = np.linalg.norm(est[:3, 3] - A[:3, 3])
    r_err = np.degrees(rotation_angle(est[:3, :3].T @ A[:3, :3]))
    assert t_err < 1e-3 and r_err < 0.005


@pytest.mark.parametrize("gain, offset", [(0.7, 0.0), (0.8, 20.0), (1.15, -10.0)])
def test_affine_brightness_recovers_a_known_motion_through_an_exposure_change(gain, offset):
    """The hand-built plane with frame t's exposure changed (grey x gain + offset): with the fit
    (`pt_affine`, `DirectConfig.affine_brightness`) the solver and the numpy tracker both recover
    the motion within 1 mm and 0.005 deg from a zero-motion start; without it the solver ends
    further off (at gain 0.7, more than 0.1 m)."""
    A = make_se3(axis_angle_to_rot([0.01, -0.03, 0.005]), [0.1, -0.05, 0.9])
    calib, (img0, img1, scan), (g0, _, pts, mask), X = _plane_inputs(A)
    changed = np.clip(gain * img1.astype(np.float64) + offset, 0, 255).round().astype(np.uint8)
    g1 = _t(grey_image(changed))[None, None]

    def errors(M):
        return np.linalg.norm(M[:3, 3] - A[:3, 3]), np.degrees(rotation_angle(M[:3, :3].T @ A[:3, :3]))

    def torch_solve(affine):
        return solve(*image_pyramids(g0, g1, 3), pts, mask, _k(calib.K2), _t(np.eye(4))[None],
                     SolverSettings(affine=affine))[-1][0].numpy()

    t_err, r_err = errors(torch_solve(True))
    assert t_err < 1e-3 and r_err < 0.005
    odo = DirectOdometry(calib, DirectConfig(affine_brightness=True, cold_start=ColdStartConfig(enabled=False)))
    odo.register_frame(img0, scan)
    t_err, r_err = errors(odo.register_frame(changed, scan))
    assert t_err < 1e-3 and r_err < 0.005
    plain = errors(torch_solve(False))[0]
    assert plain > (0.1 if gain == 0.7 else 1e-3)


@pytest.mark.parametrize("gather", [False, True])
def test_two_solves_per_pair_on_one_copy_of_its_images(gather):
    """`solve` batched as the bundled graph batches it: two pairs, each solved with a confidence's
    weights and with every weight 1 as rows 2i and 2i + 1 on one copy of the pair's images
    (GridSample's and onnxruntime's gather sampling; the refinement's check too). Every row is its
    pair solved alone with that weight."""
    from models.sampling import gathered

    motions = [make_se3(axis_angle_to_rot([0.01, -0.03, 0.005]), [0.1, -0.05, 0.9]),
               make_se3(axis_angle_to_rot([0.0, 0.02, 0.0]), [0.05, 0.0, 0.6])]
    scenes = [_plane_inputs(A) for A in motions]
    n = max(len(sc[3]) for sc in scenes) + 100
    rng = np.random.default_rng(0)
    g0, g1, pts, mask, w = [], [], [], [], []
    for calib, _, (a, b, _, _), X in scenes:
        p, m = pad_points(X, n)
        g0.append(a), g1.append(b), pts.append(_t(p)), mask.append(_t(m))
        w.append(mask[-1] * _t(rng.uniform(0.2, 1.0, m.shape)))
    K, init = _k(scenes[0][0].K2), _t(np.eye(4))[None]
    s = SolverSettings(iterations=(3, 3, 3), refine=2)
    pair = lambda a, c: torch.stack([a, c], 1).flatten(0, 1)  # noqa: E731
    with gathered(gather):
        grey1, stack2 = image_pyramids(torch.cat(g0), torch.cat(g1), 3)
        P, M, W = torch.cat(pts), torch.cat(mask), torch.cat(w)
        both = solve(grey1, stack2, pair(P, P), pair(W, M), K.repeat(4, 1), init.repeat(4, 1, 1), s,
                     mask=pair(M, M))[-1]
        for i in range(2):
            alone = image_pyramids(g0[i], g1[i], 3)
            for j, weight in enumerate((w[i], mask[i])):
                want = solve(*alone, pts[i], weight, K, init, s, mask=mask[i])[-1][0]
                np.testing.assert_allclose(both[2 * i + j].numpy(), want.numpy(), atol=1e-9)
    assert np.abs(both[0] - both[2]).max() > 1e-2  # two different pairs


def test_the_restarts_scan_check_batched_as_the_graph_batches_it():
    """The finest level's restart checked against each pair's own frame t scan (`restart_depth`,
    the gain threshold out of reach so that the scan alone decides), batched as the bundled graph
    batches it (two pairs, two weightings each, one scan per pair): every row is its pair solved
    alone, and the check keeps the restart on some rows and not on others."""
    motions = [make_se3(axis_angle_to_rot([0.01, -0.03, 0.005]), [0.1, -0.05, 0.9]),
               make_se3(axis_angle_to_rot([0.0, 0.02, 0.0]), [0.05, 0.0, 0.6])]
    scenes = [_plane_inputs(A) for A in motions]
    n = max(len(sc[3]) for sc in scenes) + 100
    rng = np.random.default_rng(0)
    g0, g1, pts, mask, w, depth = [], [], [], [], [], []
    for A, (calib, _, (a, b, _, _), X) in zip(motions, scenes):
        p, m = pad_points(X, n)
        g0.append(a), g1.append(b), pts.append(_t(p)), mask.append(_t(m))
        w.append(mask[-1] * _t(rng.uniform(0.2, 1.0, m.shape)))
        Mt = se3_inv(A)  # frame t's scan of the plane: its points seen from frame t, 3 cm of noise
        Xt = X @ Mt[:3, :3].T + Mt[:3, 3]
        u, v = np.rint(project(_t(Xt)[None], _k(calib.K2))[0][0].numpy()).astype(int).T
        d = np.zeros(b.shape[-2:], np.float32)
        ok = (u >= 0) & (u < d.shape[1]) & (v >= 0) & (v < d.shape[0])
        d[v[ok], u[ok]] = Xt[ok, 2] + rng.normal(0.0, 0.03, ok.sum())
        depth.append(_t(d)[None, None])
    K = _k(scenes[0][0].K2)
    starts = [A.copy() for A in motions]  # near the truth, as a constant-velocity start
    for A in starts:
        A[:3, 3] *= 0.97
    s = SolverSettings(iterations=(3, 3, 3), fine_restart=0.5, restart_depth=1.0)
    pair = lambda a, c: torch.stack([a, c], 1).flatten(0, 1)  # noqa: E731
    grey1, stack2 = image_pyramids(torch.cat(g0), torch.cat(g1), 3)
    P, M, W = torch.cat(pts), torch.cat(mask), torch.cat(w)
    I = _t(np.stack(starts))
    both = solve(grey1, stack2, pair(P, P), pair(W, M), K.repeat(4, 1), pair(I, I), s,
                 mask=pair(M, M), depth2=torch.cat(depth))[-1]
    kept = []
    for i in range(2):
        alone = image_pyramids(g0[i], g1[i], 3)
        for j, weight in enumerate((w[i], mask[i])):
            want = solve(*alone, pts[i], weight, K, I[i:i + 1], s, mask=mask[i], depth2=depth[i])[-1][0]
            np.testing.assert_allclose(both[2 * i + j].numpy(), want.numpy(), atol=1e-9)
            unchecked = solve(*alone, pts[i], weight, K, I[i:i + 1], replace(s, restart_depth=0.0), mask=mask[i])[-1][0]
            kept.append(bool((want - unchecked).abs().max() > 1e-9))
    assert any(kept) and not all(kept)


def test_the_next_start_is_the_weighted_solve_and_the_kept_pose_the_classical_one(monkeypatch):
    """PointPose with `pt_select`: of its one batch of two solves, `start_next` is the solve with the
    confidence's weights and, where the selection keeps the classical pose (a threshold of 0.999
    that no gain passes), the final pose is the solve with every weight 1, each as solved alone.
    Given its own start (`classical_start`, `pt_classical_chain`), the classical solve starts there
    and the weighted one still from `init`: with three steps a level, the start shows in the pose."""
    from models.config import D3LVOConfig
    from models.point_solver import pyramid_input_names
    from models.pose_points import PointPose

    pp = PointPose(D3LVOConfig.small(pose_head="points", pt_select=0.999, pt_iters=(3, 3, 3)))
    A = make_se3(axis_angle_to_rot([0.01, -0.03, 0.005]), [0.1, -0.05, 0.9])
    calib, _, (g0, g1, pts, mask), _ = _plane_inputs(A)
    logits = _t(np.random.default_rng(0).normal(0.0, 2.0, (1, 1, 44, 152)))  # a confidence far from uniform
    monkeypatch.setattr(pp, "moving_logits", lambda *args: logits)
    grey1, stack2 = image_pyramids(g0, g1, 3)
    names1, names2 = pyramid_input_names(3)
    K, init = _k(calib.K2), _t(np.eye(4))[None]
    solver = {**dict(zip(names1, grey1)), **dict(zip(names2, stack2)), "points1": pts, "point_mask1": mask,
              "image_intrinsics": K}
    out = pp(None, None, None, None, None, None, K * 0.5, init, solver)
    weighted = solve(grey1, stack2, pts, out["point_weights"], K, init, pp.settings, mask=mask)[-1]
    classical = solve(grey1, stack2, pts, mask, K, init, pp.settings, mask=mask)[-1]
    assert np.abs(weighted - classical).max() > 1e-6  # the weights matter
    np.testing.assert_allclose(out["start_next"].numpy(), weighted.numpy(), atol=1e-9)
    np.testing.assert_allclose(out["level_matrices"][-1].numpy(), classical.numpy(), atol=1e-9)
    own = _t(make_se3(axis_angle_to_rot([0.0, 0.02, 0.0]), [0.05, 0.0, 0.5]))[None]
    out = pp(None, None, None, None, None, None, K * 0.5, init, {**solver, "classical_start": own})
    from_own = solve(grey1, stack2, pts, mask, K, own, pp.settings, mask=mask)[-1]
    assert np.abs(from_own - classical).max() > 1e-5  # the start shows after three steps a level
    np.testing.assert_allclose(out["start_next"].numpy(), weighted.numpy(), atol=1e-9)
    np.testing.assert_allclose(out["level_matrices"][-1].numpy(), from_own.numpy(), atol=1e-9)


def test_zero_weight_points_are_ignored():
    """Points on the plane's left half moved as if by another object: the tracker, which weighs all
    of them, is pulled off; weight 0 on them gives the true motion again (what the learned
    confidence is for)."""
    A = make_se3(axis_angle_to_rot([0.0, 0.01, 0.0]), [0.05, 0.0, 0.6])
    calib, (img0, img1, _), (g0, g1, pts, mask), X = _plane_inputs(A)
    left = (calib.K2[0, 0] * X[:, 0] / X[:, 2] + calib.K2[0, 2]) < 310  # and a margin
    # the other object: frame t shows the left part of the image as if shifted by 25 pixels
    moved = img1.copy()
    moved[:, :280] = np.roll(img1, 25, axis=1)[:, :280]
    g1m = _t(grey_image(moved))[None, None]
    K, init = _k(calib.K2), _t(np.eye(4))[None]
    err = lambda M: float(np.linalg.norm(M[0, :3, 3].numpy() - A[:3, 3]))  # noqa: E731
    all_weighted = err(solve(*image_pyramids(g0, g1m, 3), pts, mask, K, init, SolverSettings())[-1])
    keep = mask.clone()
    keep[0, : len(X)] = _t(~left)
    right_only = err(solve(*image_pyramids(g0, g1m, 3), pts, keep, K, init, SolverSettings())[-1])
    print(f"translation error: all points {all_weighted * 1000:.1f} mm, moving half weighted 0 {right_only * 1000:.2f} mm")
    assert right_only < 2e-3 and all_weighted > 10 * right_only


def test_refinement_restores_the_static_points_a_wrong_confidence_doubted():
    """The plane's moved half at confidence 0.05, its static half wrongly doubted at 0.7: under
    the solved pose, the static points the pose explains weigh 1 again (about the share of
    residuals within Huber's 1.345 sigma), the moved ones stay down, and the refined pose is at
    least as close to the truth."""
    A = make_se3(axis_angle_to_rot([0.0, 0.01, 0.0]), [0.05, 0.0, 0.6])
    calib, (img0, img1, _), (g0, g1, pts, mask), X = _plane_inputs(A)
    left = (calib.K2[0, 0] * X[:, 0] / X[:, 2] + calib.K2[0, 2]) < 310
    Xt = X @ se3_inv(A)[:3, :3].T + se3_inv(A)[:3, 3]
    u = calib.K2[0, 0] * Xt[:, 0] / Xt[:, 2] + calib.K2[0, 2]  # in frame t, columns < 280 are shifted
    shifted, static = u < 270, u > 290
    moved = img1.copy()
    moved[:, :280] = np.roll(img1, 25, axis=1)[:, :280]
    pyr = image_pyramids(g0, _t(grey_image(moved))[None, None], 3)
    K, init = _k(calib.K2), _t(np.eye(4))[None]
    conf = mask.clone()
    conf[0, : len(X)] = _t(np.where(left, 0.05, 0.7))
    err = lambda M: float(np.linalg.norm(M[0, :3, 3].numpy() - A[:3, 3]))  # noqa: E731
    A_solved = solve(*pyr, pts, conf, K, init, SolverSettings())[-1]
    A_refined = solve(*pyr, pts, conf, K, init, SolverSettings(refine=5), mask=mask)[-1]
    M = gn.invert(A_solved)
    ref = sample_at(g0, project(pts, K)[0])[:, 0]
    w = restore_explained(M[:, :3, :3], M[:, :3, 3].unsqueeze(1), pts, ref, pyr[1][0], K, conf, mask,
                          (conf > 0.5).to(conf.dtype))[0, : len(X)].numpy()
    restored_static, restored_shifted = (w[static] == 1).mean(), (w[shifted] == 1).mean()
    print(f"restored: static {restored_static:.3f}, shifted {restored_shifted:.3f}; translation error "
          f"{err(A_solved) * 1000:.2f} mm, refined {err(A_refined) * 1000:.2f} mm")
    assert restored_static > 0.6 and restored_shifted < 0.05
    assert np.isin(w[~left], [0.7, 1.0]).all() and np.isin(w[left], [0.05, 1.0]).all()  # restored or kept
    assert err(A_refined) <= err(A_solved) + 1e-4 and err(A_refined) < 2e-3


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of img at (u, v), for points inside it."""
    u0, v0 = np.floor(u).astype(int).clip(0, img.shape[1] - 2), np.floor(v).astype(int).clip(0, img.shape[0] - 2)
    a, b = u - u0, v - v0
    return ((1 - a) * (1 - b) * img[v0, u0] + a * (1 - b) * img[v0, u0 + 1] + (1 - a) * b * img[v0 + 1, u0]
            + a * b * img[v0 + 1, u0 + 1])


def _consensus_gain_numpy(A, A_c, grey0, grey1, X, w, K, cap=2.0):
    """The MSAC gain written out in numpy: per point, min(r^2 / (cap sigma)^2, 1) under the
    classical pose minus under the weighted one, averaged over the trusted points."""
    gains, trusted = _msac_gains_numpy(A, A_c, grey0, grey1, X, w, K, cap)
    return float(gains[trusted].mean())


def _msac_gains_numpy(A, A_c, grey0, grey1, X, w, K, cap=2.0):
    """`_consensus_gain_numpy` point by point: each point's gain and whether it is trusted."""
    proj = lambda P: (K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2], K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2])  # noqa: E731
    ref = _bilinear(grey0, *proj(X))
    rs, seen = [], []
    for pose in (A, A_c):
        M = se3_inv(pose)
        u, v = proj(X @ M[:3, :3].T + M[:3, 3])
        inside = (u >= 0) & (u <= grey1.shape[1] - 1) & (v >= 0) & (v <= grey1.shape[0] - 1)
        rs.append(np.where(inside, _bilinear(grey1, u.clip(0, grey1.shape[1] - 1), v.clip(0, grey1.shape[0] - 1)) - ref,
                           0.0))
        seen.append(inside)
    ok = seen[0] & seen[1] & (w > 0)
    sigma = 1.4826 * min(np.median(np.abs(rs[0][ok])), np.median(np.abs(rs[1][ok])))
    cost = [np.minimum(r**2 / (cap * sigma) ** 2, 1.0) for r in rs]
    return cost[1] - cost[0], ok & (w >= 0.5)


def test_consensus_gain_tells_a_mover_from_a_false_detection():
    """The plane's left half moved (another object) or not (a static scene), its points weighted
    0 either way, as a confidence that flags them would. With the mover, the classical pose
    (every point at full weight) is pulled off the static right half, which the weighted pose
    explains: the gain is large, and above the bundled threshold pt_select = 0.003. Without it
    both poses are the true motion and the gain is nil, so `pt_select` keeps the classical pose.
    Both figures agree with the gain written out in numpy."""
    A = make_se3(axis_angle_to_rot([0.0, 0.01, 0.0]), [0.05, 0.0, 0.6])
    calib, (img0, img1, _), (g0, g1, pts, mask), X = _plane_inputs(A)
    left = (calib.K2[0, 0] * X[:, 0] / X[:, 2] + calib.K2[0, 2]) < 310
    moved = img1.copy()
    moved[:, :280] = np.roll(img1, 25, axis=1)[:, :280]
    K, init = _k(calib.K2), _t(np.eye(4))[None]
    weight = mask.clone()
    weight[0, : len(X)] = _t(~left)
    gains = {}
    for case, frame_t in (("mover", moved), ("static", img1)):
        g1 = _t(grey_image(frame_t))[None, None]
        pyr = image_pyramids(g0, g1, 3)
        A_w = solve(*pyr, pts, weight, K, init, SolverSettings())[-1]
        A_c = solve(*pyr, pts, mask, K, init, SolverSettings())[-1]
        gain = float(consensus_gain(A_w, A_c, g0, g1, pts, weight, K)[0])
        expected = _consensus_gain_numpy(A_w[0].numpy(), A_c[0].numpy(), grey_image(img0), grey_image(frame_t), X,
                                         weight[0, : len(X)].numpy(), calib.K2)
        print(f"{case}: gain {gain:.4f} (numpy {expected:.4f}); classical pose off by "
              f"{np.linalg.norm(A_c[0, :3, 3].numpy() - A[:3, 3]) * 1000:.1f} mm")
        assert abs(gain - expected) < 1e-4
        # point by point (what scripts/selection_rules.py reads the gain's spread from)
        per, trusted = msac_gains(A_w, A_c, g0, g1, pts, weight, K)
        per_np, trusted_np = _msac_gains_numpy(A_w[0].numpy(), A_c[0].numpy(), grey_image(img0),
                                               grey_image(frame_t), X, weight[0, : len(X)].numpy(), calib.K2)
        assert np.array_equal(trusted[0, : len(X)].numpy() > 0, trusted_np) and not trusted[0, len(X):].any()
        diff = np.abs(per[0, : len(X)].numpy()[trusted_np] - per_np[trusted_np]).max()
        print(f"{case}: point by point within {diff:.1e} of numpy, {trusted_np.sum()} trusted")
        assert diff < 5e-4
        gains[case] = gain
    assert gains["mover"] > 0.1 and abs(gains["static"]) < 0.001


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rotations_differ_by_the_angle_between_them(dtype):
    """Two rotations about one axis differ by the difference of their angles: 0.049 and 0.051
    degrees apart fall either side of a 0.05 degree threshold in float32 too (where the trace's
    cosine cannot tell them apart), 120 and 179.97 degrees apart (past 90, where the sine falls
    again, to that of 0.03 degrees) differ,
    and random pairs agree with numpy's angle of A^T B."""
    axis = np.array([0.3, 0.9, -0.2]) / np.linalg.norm([0.3, 0.9, -0.2])
    base = np.radians(1.3)

    def pose(rad, ax=axis):
        return torch.tensor(make_se3(axis_angle_to_rot(ax * rad), [0.1, 0.0, 0.8]), dtype=dtype)[None]

    for apart, differ in ((0.049, False), (0.051, True), (0.0, False), (120.0, True), (179.97, True)):
        got = rotations_differ(pose(base), pose(base + np.radians(apart)), 0.05)
        assert bool(got[0]) is differ, apart
    rng = np.random.default_rng(3)
    for _ in range(20):
        A = axis_angle_to_rot(rng.normal(0.0, 0.5, 3))
        B = A @ axis_angle_to_rot(rng.normal(0.0, np.radians(0.05), 3))
        angle = np.degrees(rotation_angle(A.T @ B))
        if abs(angle - 0.05) > 2e-3:  # float32 rounding apart
            to = lambda R: torch.tensor(make_se3(R, [0.0, 0.0, 0.0]), dtype=dtype)[None]  # noqa: E731
            assert bool(rotations_differ(to(A), to(B), 0.05)[0]) == bool(angle > 0.05)


@dataclass
class _Mover:
    """The hand-built plane whose left half moves in frame t's image only (weighted 0, `right` the
    other points), solved with those weights and with every weight 1, as the selection tests read it."""
    A: np.ndarray
    calib: object
    X: np.ndarray
    img1: np.ndarray
    right: np.ndarray
    g0: torch.Tensor
    g1: torch.Tensor
    pts: torch.Tensor
    mask: torch.Tensor
    weight: torch.Tensor
    K: torch.Tensor
    weighted: torch.Tensor
    classical: torch.Tensor
    gain: float  # the weighted pose's MSAC gain over the classical one (`consensus_gain`)


def _mover_on_the_plane() -> _Mover:
    A = make_se3(axis_angle_to_rot([0.0, 0.01, 0.0]), [0.05, 0.0, 0.6])
    calib, (_, img1, _), (g0, _, pts, mask), X = _plane_inputs(A)
    moved = img1.copy()
    moved[:, :280] = np.roll(img1, 25, axis=1)[:, :280]
    g1 = _t(grey_image(moved))[None, None]
    right = (calib.K2[0, 0] * X[:, 0] / X[:, 2] + calib.K2[0, 2]) >= 310
    weight = mask.clone()
    weight[0, : len(X)] = _t(right)
    pyramids, K, init = image_pyramids(g0, g1, 3), _k(calib.K2), _t(np.eye(4))[None]
    settings = SolverSettings((3, 3, 3))
    weighted = solve(*pyramids, pts, weight, K, init, settings, mask=mask)[-1]
    classical = solve(*pyramids, pts, mask, K, init, settings, mask=mask)[-1]
    gain = float(consensus_gain(weighted, classical, g0, g1, pts, weight, K)[0])
    assert gain > 0.1
    return _Mover(A, calib, X, img1, right, g0, g1, pts, mask, weight, K, weighted, classical, gain)


def _kept_pose(monkeypatch, case: _Mover, logits=None, scan: np.ndarray | None = None, **setting) -> torch.Tensor:
    """The pose PointPose keeps on `case` under the selection `setting`, its confidence the case's
    weights (`logits`: the confidence net's stand-in, default 0 everywhere)."""
    from models.config import D3LVOConfig
    from models.point_solver import pyramid_input_names
    from models.pose_points import PointPose

    pp = PointPose(D3LVOConfig.small(pose_head="points", pt_iters=(3, 3, 3), **setting))
    monkeypatch.setattr(pp, "moving_logits", logits or (lambda *args: torch.zeros(1, 1, 44, 152)))
    monkeypatch.setattr(pp, "point_confidence", lambda *args: case.weight)
    grey1, stack2 = image_pyramids(case.g0, case.g1, 3)
    names1, names2 = pyramid_input_names(3)
    solver = {**dict(zip(names1, grey1)), **dict(zip(names2, stack2)), "points1": case.pts, "point_mask1": case.mask,
              "image_intrinsics": case.K}
    if scan is not None:
        solver["scan_depth2"] = _t(scan)[None, None]
    init = _t(np.eye(4))[None]
    return pp(None, None, None, None, None, None, case.K * 0.5, init, solver)["level_matrices"][-1]


@pytest.mark.parametrize("margin, kept", [(0.9, "weighted"), (1.1, "classical")])
def test_the_weighted_pose_is_kept_only_where_its_rotation_differs(monkeypatch, margin, kept):
    """PointPose with `pt_select` and `pt_select_rotation`: with a mover (the plane's left half,
    weighted 0) the weighted pose explains the trusted points far better than the classical one;
    it is kept with the rotation threshold just under the angle between the two poses (numpy's),
    and the classical pose is kept with the threshold just over it."""
    case = _mover_on_the_plane()
    angle = np.degrees(rotation_angle(case.weighted[0, :3, :3].numpy().T @ case.classical[0, :3, :3].numpy()))
    assert angle > 0.01
    got = _kept_pose(monkeypatch, case, pt_select=0.01, pt_select_rotation=float(angle * margin))
    want = case.weighted if kept == "weighted" else case.classical
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=1e-9)


@pytest.mark.parametrize("margin, kept", [(0.9, "weighted"), (1.1, "classical")])
def test_the_weighted_pose_is_kept_only_where_the_classical_pose_leaves_points_unexplained(monkeypatch, margin,
                                                                                           kept):
    """PointPose with `pt_select_unexplained`: the confidence is read a second time with the
    classical pose as the motion (the second `moving_logits` call gets exactly that pose), and the
    weighted pose is kept only where more than the threshold's share of frame t-1's points is
    distrusted. Here the second reading distrusts the plane's left half, whose share of the
    valid points is counted in numpy: a threshold just under it keeps the weighted pose, just over
    it the classical one."""
    case = _mover_on_the_plane()
    share = float((~case.right).sum()) / len(case.X)  # the left half, distrusted, among the valid points
    assert 0.2 < share < 0.8 and int(case.mask.sum()) == len(case.X)
    motions = []

    def logits(*args):
        motions.append(args[-1])
        return torch.zeros(1, 1, 44, 152)

    got = _kept_pose(monkeypatch, case, logits, pt_select=0.01, pt_select_unexplained=share * margin)
    assert len(motions) == 2 and np.array_equal(motions[0].numpy(), np.eye(4)[None])
    np.testing.assert_allclose(motions[1].numpy(), case.classical.numpy(), atol=1e-9)
    want = case.weighted if kept == "weighted" else case.classical
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=1e-9)


@pytest.mark.parametrize("rule, margin, kept", [("veto", 1.1, "weighted"), ("veto", 0.9, "classical"),
                                                 ("pass", 1.1, "weighted"), ("pass", 0.9, "classical")])
def test_frame_ts_scan_judges_between_the_weighted_and_the_classical_pose(monkeypatch, rule, margin, kept):
    """PointPose with `pt_select_scan` (veto) and `pt_select_scan_pass` (pass): frame t's scan is the
    plane seen from the true motion; the mover (the plane's left half moved in the image only,
    weighted 0) pulls the classical pose, so the weighted pose fits the scan better. The ratio of
    their depth errors over the trusted points comes from the numpy tracker's `lidar_depth_error`.
    Veto (the photometric test passes): a ratio threshold just over it keeps the weighted pose,
    just under it the classical one. Pass (the photometric test fails, pt_select 0.99): a threshold
    just over the ratio keeps the weighted pose anyway, just under it not."""
    case = _mover_on_the_plane()
    A, K2 = case.A, case.calib.K2
    h, w = case.img1.shape[:2]

    def seen_from(motion: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows, columns (the nearest pixel) and depths in frame t of frame t-1's points X under the
        motion (frame t in frame t-1), those landing in the image."""
        M = np.linalg.inv(motion)
        Xt = X @ M[:3, :3].T + M[:3, 3]
        u, v = np.rint(Xt[:, :2] / Xt[:, 2:] * np.diag(K2)[:2] + K2[:2, 2]).astype(int).T
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        return v[inside], u[inside], Xt[inside, 2]

    # frame t's scan: frame t-1's points seen from frame t (every second one: gaps, as a scan has)
    depth = np.zeros((h, w), np.float32)
    rows, cols, z = seen_from(A, case.X[::2])
    depth[rows, cols] = z
    errors = [direct.lidar_depth_error(case.X[case.right], P[0].numpy(), depth, K2)
              for P in (case.weighted, case.classical)]
    print(f"depth errors: weighted {errors[0]:.5f}, classical {errors[1]:.5f}")
    ratio = errors[0] / errors[1]
    assert 0 < ratio < 0.9, errors
    assert case.gain < 0.99  # the pass cases' photometric test fails
    setting = dict(pt_select=0.01, pt_select_scan=ratio * margin) if rule == "veto" else \
        dict(pt_select=0.99, pt_select_scan_pass=ratio * margin)
    got = _kept_pose(monkeypatch, case, scan=depth, **setting)
    want = case.weighted if kept == "weighted" else case.classical
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=1e-9)
    # where a pose puts no trusted point on a return, the scan is no evidence and the photometric
    # test decides: the scan without the returns under the classical pose's trusted points (the
    # weighted pose's land on others), and with none under either pose's
    def without_returns_under(pose: torch.Tensor) -> np.ndarray:
        scan = depth.copy()
        rows, cols, _ = seen_from(pose[0].numpy(), case.X[case.right])
        scan[rows, cols] = 0.0
        return scan

    empty = np.where(np.arange(w)[None, :] < 300, depth, 0.0).astype(np.float32)
    photometric = case.weighted if rule == "veto" else case.classical
    for scan, sees in ((without_returns_under(case.classical), (True, False)),
                       (without_returns_under(case.weighted), (False, True)), (empty, (False, False))):
        errors = [direct.lidar_depth_error(case.X[case.right], P[0].numpy(), scan, K2)
                  for P in (case.weighted, case.classical)]
        assert tuple(np.isfinite(errors)) == sees, errors
        np.testing.assert_allclose(_kept_pose(monkeypatch, case, scan=scan, **setting).numpy(), photometric.numpy(),
                                   atol=1e-9)
    # without a scan at all (training's samples): the photometric test decides
    np.testing.assert_allclose(_kept_pose(monkeypatch, case, **setting).numpy(), photometric.numpy(), atol=1e-9)


@pytest.mark.parametrize("key, value", [("pt_select_scan_pass", 1.01), ("pt_select_scan_pass", -0.1),
                                        ("pt_select_scan", 100.0)])
def test_the_scan_judges_ratios_are_checked(key, value):
    """A pass above 1 would keep a weighted pose that fits the scan worse; both ratios are refused
    outside their ranges, by name."""
    from models.config import D3LVOConfig

    with pytest.raises(ValueError, match=key):
        D3LVOConfig.small(pose_head="points", **{key: value})


def test_scan_errors_of_two_pairs_are_each_pairs_own():
    """`PointPose.scan_errors` batched over two pairs (each with its weighted and classical pose,
    its own points, weights and scan) gives each pose's numpy `lidar_depth_error` over that pair's
    trusted points against that pair's scan; the scans differ, so a row read against the other
    pair's scan would show."""
    from models.pose_points import PointPose

    rng = np.random.default_rng(2)
    K = np.array([[100.0, 0, 10], [0, 100.0, 10], [0, 0, 1]])
    X = [np.stack([rng.uniform(-0.8, 0.8, 60), rng.uniform(-0.8, 0.8, 60), rng.uniform(4, 12, 60)], 1) for _ in range(2)]
    weight = [rng.uniform(0.0, 1.0, 60) for _ in range(2)]
    depths = [np.where(rng.random((21, 21)) < 0.6, rng.uniform(3, 12, (21, 21)), 0).astype(np.float32)
              for _ in range(2)]
    W = [make_se3(axis_angle_to_rot([0, 0.01 * j, 0]), [0.0, 0.0, 0.2 + 0.3 * j]) for j in range(2)]
    C = [make_se3(axis_angle_to_rot([0.02 * j, 0, 0]), [0.1, 0.0, 0.5 * j]) for j in range(2)]
    solver = {"points1": _t(np.stack(X)), "image_intrinsics": _k(K).repeat(2, 1),
              "scan_depth2": _t(np.stack(depths))[:, None]}
    got = PointPose.scan_errors(_t(np.stack(W)), _t(np.stack(C)), solver, _t(np.stack(weight))).numpy()
    for i in range(2):
        trusted = X[i][weight[i] >= 0.5]
        want = [direct.lidar_depth_error(trusted, A, depths[i], K) for A in (W[i], C[i])]
        np.testing.assert_allclose(got[i], want, rtol=1e-6)
    assert direct.lidar_depth_error(X[0][weight[0] >= 0.5], W[0], depths[1], K) != pytest.approx(got[0, 0])


def _real_pair():
    from conftest import shared_path

    return KittiSequence.open(shared_path("kitti_raw_snippet", "sequences", "r0926"))


def _pair_11_12(cfg: DirectConfig):
    """The real pair 11-12 as the classical mode tracks it after frames 10 and 11: the sequence,
    the constant-velocity start and both frames."""
    seq = _real_pair()
    odo = DirectOdometry(seq.calib, cfg)
    for i in (10, 11):
        odo.register_frame(seq.image(i), seq.scan(i))
    return seq, odo.motion2.copy(), odo._prev, odo._frame(seq.image(12), seq.scan(12))


@pytest.mark.parametrize("scale_every, refine, affine, stride",
                         [(3, 0, False, 1), (1, 0, False, 1), (3, 5, False, 1), (3, 0, True, 1), (3, 0, True, 4)])
def test_confidence_one_is_the_numpy_tracker(scale_every, refine, affine, stride):
    """On a real frame pair, the solver with every confidence 1 gives the motion of
    `d3lvo run --method direct` (numpy, float64, its own loop with a break) within 1e-6 m, with
    the Huber threshold re-estimated every third step (the default) and at every step, with
    the refinement after the finest level (which restores nothing when every weight is 1), with
    frame t's grey fitted as a ref + b at every step, and with the threshold's median over every
    fourth point of the list (the numpy tracker picks them by their place among the points in
    view, the graph by a strided slice of the padded list)."""
    seq = _real_pair()
    cfg = DirectConfig(scale_every=scale_every, refine=refine, affine_brightness=affine, median_stride=stride)
    odo = DirectOdometry(seq.calib, cfg)
    for i in (8, 9):
        odo.register_frame(seq.image(i), seq.scan(i))
    init, X = odo.motion2.copy(), odo._prev.points
    want = odo.register_frame(seq.image(10), seq.scan(10))
    pts, mask = pad_points(X, cfg.points.capacity)
    images = [_t(grey_image(seq.image(i)))[None, None] for i in (9, 10)]
    got = solve(*image_pyramids(*images, 3), _t(pts), _t(mask), _k(seq.calib.K2), _t(init)[None],
                SolverSettings(cfg.iterations, cfg.stop_step, cfg.damping, cfg.scale_every, refine, affine,
                               median_stride=stride))[-1][0].numpy()
    assert np.linalg.norm(want[:3, 3]) > 0.1  # the car moves
    assert np.abs(got[:3, 3] - want[:3, 3]).max() < 1e-6 and np.abs(got[:3, :3] - want[:3, :3]).max() < 1e-7
    if stride > 1:  # the sampled median moves the motion by far more than the tolerance
        every = DirectOdometry(seq.calib, replace(cfg, median_stride=1))
        for i in (8, 9):
            every.register_frame(seq.image(i), seq.scan(i))
        assert np.abs(every.register_frame(seq.image(10), seq.scan(10))[:3, 3] - want[:3, 3]).max() > 1e-5


def test_fine_restart_is_the_numpy_trackers():
    """On a real frame pair where solving the finest level alone from the constant-velocity start
    explains the points better than coarse to fine (it moves the motion by over 1 cm), the solver
    with every confidence 1 keeps the same motion as the numpy tracker's `fine_restart` (float64,
    its own cost in numpy) within 1e-6 m."""
    cfg = DirectConfig(affine_brightness=True, fine_restart=0.005)
    seq, init, prev, cur = _pair_11_12(cfg)
    want = track(prev, cur, init, cfg)
    coarse_to_fine = track(prev, cur, init, replace(cfg, fine_restart=0.0))
    assert np.linalg.norm(want[:3, 3] - coarse_to_fine[:3, 3]) > 0.01  # the restart is kept here
    pts, mask = pad_points(prev.points, cfg.points.capacity)
    images = [_t(grey_image(seq.image(i)))[None, None] for i in (11, 12)]
    got = solve(*image_pyramids(*images, 3), _t(pts), _t(mask), _k(seq.calib.K2), _t(init)[None],
                SolverSettings(cfg.iterations, affine=True, fine_restart=0.005))[-1][0].numpy()
    assert np.abs(got[:3, 3] - want[:3, 3]).max() < 1e-6 and np.abs(got[:3, :3] - want[:3, :3]).max() < 1e-7


def test_lidar_depth_error_by_hand():
    """Frame t-1's points moved 1 m forward (frame t 1 m ahead) against a hand-made scan of frame
    t: the median |d - z| / z over the points that land on a return, z above 0.5 m and inside the
    image, in numpy and in the graph (whose untrusted points do not count); no such point: inf
    (numpy), 1e9 (graph)."""
    K = np.array([[100.0, 0, 10], [0, 100.0, 10], [0, 0, 1]])
    A = make_se3(np.eye(3), [0.0, 0.0, 1.0])
    # z after the move: 9, 4, 19, 0.4 (too near), 9 (off the image), 4 (no return), 9 (untrusted)
    X = np.array([[0, 0, 10], [0.4, 0, 5], [0, -0.95, 20], [0, 0, 1.4], [2.0, 0, 10], [0, 0.4, 5], [0.9, 0.9, 10.0]])
    depth = np.zeros((21, 21), np.float32)
    depth[10, 10], depth[10, 20], depth[5, 10] = 9.9, 4.4, 16.15  # errors 0.1, 0.1, 0.15
    depth[20, 20] = 1.0  # under the untrusted point: error 8 / 9
    depth[11, 11] = 50.0  # where the point off the image would wrap to in a flattened map
    assert direct.lidar_depth_error(X[:3], A, depth, K) == pytest.approx(0.1)
    assert direct.lidar_depth_error(X, A, depth, K) == pytest.approx(np.median([0.1, 0.1, 0.15, 8 / 9]))
    assert direct.lidar_depth_error(X[3:6], A, depth, K) == np.inf
    trusted = np.array([1, 1, 1, 1, 1, 1, 0.0])
    got = lidar_depth_error(_t(A)[None], _t(X)[None], _t(trusted)[None], _t(depth)[None, None], _k(K))
    assert float(got[0]) == pytest.approx(np.median([0.1, 0.1, 0.15]))
    none = lidar_depth_error(_t(A)[None], _t(X[3:6])[None], _t(trusted[3:6])[None], _t(depth)[None, None], _k(K))
    assert float(none[0]) == 1e9


def test_lidar_depth_error_rows_on_their_own_pairs_scan():
    """Batched as the solver batches it (two pairs, two poses each, rows 2i and 2i + 1 on pair i's
    depth map), each row's error is that pose's on its own pair alone; the two pairs' maps differ,
    so a row read against the other pair's map would show."""
    rng = np.random.default_rng(1)
    K = np.array([[100.0, 0, 10], [0, 100.0, 10], [0, 0, 1]])
    X = np.stack([rng.uniform(-0.8, 0.8, 50), rng.uniform(-0.8, 0.8, 50), rng.uniform(4, 12, 50)], 1)
    depths = [np.where(rng.random((21, 21)) < 0.6, rng.uniform(3, 12, (21, 21)), 0).astype(np.float32)
              for _ in range(2)]
    poses = [make_se3(axis_angle_to_rot([0, 0.01 * j, 0]), [0.0, 0.0, 0.3 * j]) for j in range(4)]
    got = lidar_depth_error(_t(np.stack(poses)), _t(X)[None].repeat(4, 1, 1), torch.ones(4, 50, dtype=D),
                            _t(np.stack(depths))[:, None], _k(K).repeat(4, 1))
    for j, A in enumerate(poses):
        assert float(got[j]) == pytest.approx(direct.lidar_depth_error(X, A, depths[j // 2], K), rel=1e-6)
    assert direct.lidar_depth_error(X, poses[0], depths[0], K) != pytest.approx(
        direct.lidar_depth_error(X, poses[0], depths[1], K))


@pytest.mark.parametrize("ratio, kept", [(0.9, "restart"), (0.7, "coarse to fine")])
def test_restart_depth_is_the_numpy_trackers(ratio, kept):
    """On a real pair where the finest level's restart fits frame t's LiDAR scan better (its depth
    error is 0.78 of coarse to fine's) but is not kept by its photometric gain (the gain threshold
    set out of reach here), the restart is kept where the ratio allows it, and the graph with
    every confidence 1 keeps the same motion as the numpy tracker, within 1e-6 m."""
    cfg = DirectConfig(affine_brightness=True, fine_restart=0.5, restart_depth=ratio)
    seq, init, prev, cur = _pair_11_12(cfg)
    want = track(prev, cur, init, cfg)
    coarse_to_fine = track(prev, cur, init, replace(cfg, restart_depth=0.0))
    moved = np.linalg.norm(want[:3, 3] - coarse_to_fine[:3, 3])
    assert (moved > 0.01) if kept == "restart" else (moved == 0)
    pts, mask = pad_points(prev.points, cfg.points.capacity)
    images = [_t(grey_image(seq.image(i)))[None, None] for i in (11, 12)]
    got = solve(*image_pyramids(*images, 3), _t(pts), _t(mask), _k(seq.calib.K2), _t(init)[None],
                SolverSettings(cfg.iterations, affine=True, fine_restart=0.5, restart_depth=ratio),
                depth2=_t(cur.depth)[None, None])[-1][0].numpy()
    assert np.abs(got[:3, 3] - want[:3, 3]).max() < 1e-6 and np.abs(got[:3, :3] - want[:3, :3]).max() < 1e-7


def test_consensus_gain_is_the_numpy_trackers():
    """The runtime's numpy `direct.consensus_gain` (which picks the classical mode's fine restart)
    is the graph's `consensus_gain` with every weight 1, on a real pair for three pairs of motions
    (rest, a guess, the tracked motion), both ways round; swapped, the gain changes sign."""
    seq = _real_pair()
    odo = DirectOdometry(seq.calib, DirectConfig())
    prev, cur = odo._frame(seq.image(11), seq.scan(11)), odo._frame(seq.image(12), seq.scan(12))
    pts, mask = pad_points(prev.points, 2048)
    g0, g1 = (_t(f.levels[0].stack[..., 0])[None, None] for f in (prev, cur))
    rest, guess = np.eye(4), make_se3(axis_angle_to_rot([0, 0.01, 0]), [0.0, 0.0, 0.5])
    tracked = track(prev, cur, rest, DirectConfig())
    for A, B in ((tracked, rest), (tracked, guess), (guess, rest)):
        want = direct.consensus_gain(prev, cur, A, B)
        got = float(consensus_gain(_t(A)[None], _t(B)[None], g0, g1, _t(pts), _t(mask), _k(seq.calib.K2))[0])
        assert got == pytest.approx(want, abs=1e-5)
        assert direct.consensus_gain(prev, cur, B, A) == pytest.approx(-want, abs=1e-9)
    assert direct.consensus_gain(prev, cur, tracked, rest) > 0.02  # the tracked motion explains the pair better


def test_onnx_runtime_equals_torch_and_tracks(points_model, small_synth, tmp_path):
    """The exported graph, fed by the torch-free runtime at the camera's own size (620x188, traced
    at another), gives torch's trajectory; both follow the rendered motion to within 3 % per pair."""
    from d3lvo_deploy.geometry import relatives
    from d3lvo_deploy.pipeline import RunConfig, run_sequence
    from d3lvo_deploy.poses import read_poses
    from models.checkpoint import build_model, load_checkpoint
    from models.predict import predict_sequence

    ck, onnx_dir = points_model
    torch_traj = predict_sequence(build_model(load_checkpoint(ck)), small_synth)
    run_sequence(KittiSequence.open(small_synth), onnx_dir, RunConfig(out=tmp_path / "p.txt"))
    est = read_poses(tmp_path / "p.txt").poses
    np.testing.assert_allclose(est[:, :3, 3], torch_traj[:, :3, 3], atol=1e-4)
    gt = relatives(KittiSequence.open(small_synth).ground_truth.poses)
    err = np.linalg.norm(relatives(est)[:, :3, 3] - gt[:, :3, 3], axis=1)
    assert np.all(err < 0.03 * np.linalg.norm(gt[:, :3, 3], axis=1))


def test_restart_depth_graph_takes_frame_ts_scan_and_equals_torch(points_model, small_synth, tmp_path):
    """Exported with `pt_restart_depth` (the fixture's ratio 1: the restart is kept wherever it fits
    frame t's scan better), the flow+pose graph takes frame t's LiDAR depth (`scan_depth2`), which
    the torch-free runtime feeds at the camera's own size, and gives torch's trajectory; the scan
    changes which pose is kept on some pairs (the trajectory differs from the one without it). A
    graph without the check has no such input: `test_export_set_reaches_the_graph`."""
    from d3lvo_deploy.manifest import load_manifest
    from d3lvo_deploy.pipeline import RunConfig, run_sequence
    from d3lvo_deploy.poses import read_poses
    from models.checkpoint import build_model, load_checkpoint
    from models.predict import predict_sequence

    ck, onnx_dir = load_checkpoint(points_model[0]), points_model[1]
    assert ck["config"].pt_restart_depth == 1.0
    assert "scan_depth2" in [i["name"] for i in load_manifest(onnx_dir)["stages"]["flowpose"]["inputs"]]
    torch_traj = predict_sequence(build_model(ck), small_synth)
    without = predict_sequence(build_model({**ck, "config": replace(ck["config"], pt_restart_depth=0.0)}),
                               small_synth)
    run_sequence(KittiSequence.open(small_synth), onnx_dir, RunConfig(out=tmp_path / "p.txt"))
    est = read_poses(tmp_path / "p.txt").poses
    np.testing.assert_allclose(est[:, :3, 3], torch_traj[:, :3, 3], atol=1e-4)
    assert np.abs(torch_traj[:, :3, 3] - without[:, :3, 3]).max() > 1e-5


def test_scan_judge_graph_takes_frame_ts_scan_and_equals_torch(scan_judge_model, small_synth, tmp_path):
    """With `pt_select_scan_pass` (`scan_judge_model`), the flow+pose graphs take frame t's scan
    and the classical solve does not; the torch-free runtime, which solves the classical mode
    beside the network, gives torch's trajectory under the same settings, which differs from the
    classical pose kept always. Kept always, the classical pose started from the previous classical
    one (`pt_classical_chain`) is the numpy tracker's trajectory (`--method direct`)."""
    from d3lvo_deploy.manifest import load_manifest
    from d3lvo_deploy.pipeline import RunConfig, run_sequence
    from d3lvo_deploy.poses import read_poses
    from models.checkpoint import build_model, load_checkpoint
    from models.predict import predict_sequence

    ck_path, onnx_dir = scan_judge_model
    stages = load_manifest(onnx_dir)["stages"]
    takes = {name: "scan_depth2" in [i["name"] for i in stage["inputs"]] for name, stage in stages.items()}
    assert takes == {"completion": False, "encoder": False, "flowpose": True, "classical": False,
                     "flowpose_weighted": True}
    ck = load_checkpoint(ck_path)
    torch_traj = predict_sequence(build_model(ck), small_synth)
    classical = predict_sequence(build_model({**ck, "config": replace(ck["config"], pt_select_scan_pass=0.0)}),
                                 small_synth)
    run_sequence(KittiSequence.open(small_synth), onnx_dir, RunConfig(out=tmp_path / "p.txt"))
    est = read_poses(tmp_path / "p.txt").poses
    np.testing.assert_allclose(est[:, :3, 3], torch_traj[:, :3, 3], atol=1e-4)
    assert np.abs(torch_traj[:, :3, 3] - classical[:, :3, 3]).max() > 1e-4
    seq = KittiSequence.open(small_synth)
    tracker = DirectOdometry(seq.calib, DirectConfig.of_model(ck["config"].to_dict()))
    direct = np.array([tracker.step(seq.image(i), seq.scan(i)) for i in range(len(seq))])
    np.testing.assert_allclose(classical[:, :3, 3], direct[:, :3, 3], atol=2e-5)


def test_parity_of_a_graph_that_chains_its_classical_solve(scan_judge_model, small_synth):
    """`d3lvo parity` on a model whose classical solve starts from its own previous pose
    (`scan_judge_model`): each side feeds its own `classical_next` back, and the chains agree."""
    from export.parity import POSE_R_TOL, POSE_T_TOL, run_parity

    rep = run_parity(*scan_judge_model, small_synth, frames=4)
    assert rep.passed, rep.to_dict()
    assert rep.stages["flowpose"]["classical_next"].max_abs < 1e-4
    assert rep.stages["flowpose"]["select_kept"].max_abs == 0  # the same choice on both sides, pair by pair
    assert rep.chained_t_m <= POSE_T_TOL and rep.chained_r_deg <= POSE_R_TOL


def test_runtime_feeds_frame_ts_own_scan():
    """Where the bundled graph checks the restart against the scan, the runtime makes each frame's
    LiDAR depth at the camera's size from its whole scan (the cull before it drops no return that
    lands in the image) and feeds the pair's frame t's, not frame t-1's."""
    from d3lvo_deploy.bundled import bundled_model_dir
    from d3lvo_deploy.odometry import Odometry, clean_scan
    from d3lvo_deploy.points import solver_feeds
    from d3lvo_deploy.projection import sparse_depth

    seq = _real_pair()
    odo = Odometry(bundled_model_dir(), seq.calib)
    assert odo.takes_depth
    prev, cur = (odo.prepare(seq.image(i), seq.scan(i)).solver for i in (4, 5))
    for frame, i in ((prev, 4), (cur, 5)):
        h, w = seq.image(i).shape[:2]
        want = sparse_depth(clean_scan(seq.scan(i)), seq.calib.P_velo_to_image2, w, h)
        assert (want > 0).sum() > 10000 and np.array_equal(frame.depth, want)
    assert np.array_equal(solver_feeds(prev, cur, seq.calib.K2, 2048)["scan_depth2"][0, 0], cur.depth)
    assert not np.array_equal(prev.depth, cur.depth)


def test_prepare_on_two_threads_gives_the_same_frame(monkeypatch):
    """With two threads, `prepare` makes the solver's finest level and picks its points on its
    helper thread beside the scan's cull and the network's inputs; every array is the one the
    single-threaded preparation gives."""
    import threading

    from d3lvo_deploy import odometry
    from d3lvo_deploy.bundled import bundled_model_dir

    seq = _real_pair()
    odo = odometry.Odometry(bundled_model_dir(), seq.calib)
    where = []
    for name in ("finest_level", "textured_points"):
        def spy(*args, _real=getattr(odometry, name), _name=name):
            where.append((_name, threading.current_thread().name))
            return _real(*args)

        monkeypatch.setattr(odometry, name, spy)
    one, two = (odo.prepare(seq.image(6), seq.scan(6), threads=n) for n in (1, 2))
    here = threading.current_thread().name
    assert where[:2] == [("finest_level", here), ("textured_points", here)]
    assert [n for n, _ in where[2:]] == ["finest_level", "textured_points"]
    assert all(t.startswith("d3lvo-prepare") for _, t in where[2:])
    assert len(one.solver.points) > 1000
    for a, b in ((one.rgb, two.rgb), (one.inv, two.inv), (one.solver.points, two.solver.points),
                 (one.solver.depth, two.solver.depth), *zip(one.solver.pyramid, two.solver.pyramid)):
        assert np.array_equal(a, b)


def test_the_preparing_thread_ends_with_its_odometry():
    """`prepare`'s helper thread belongs to its Odometry: once the object is gone, so is the thread
    (a process that opens trackers one after another does not collect idle threads)."""
    import gc
    import threading
    import weakref

    from d3lvo_deploy import odometry
    from d3lvo_deploy.bundled import bundled_model_dir

    seq = _real_pair()
    before = set(threading.enumerate())  # other trackers of this process keep theirs
    odo = odometry.Odometry(bundled_model_dir(), seq.calib)
    odo.prepare(seq.image(6), seq.scan(6), threads=2)
    helpers = [t for t in set(threading.enumerate()) - before if t.name.startswith("d3lvo-prepare")]
    assert len(helpers) == 1
    gone = weakref.ref(odo)
    del odo
    gc.collect()
    assert gone() is None
    for t in helpers:
        t.join(timeout=10)
    assert not any(t.is_alive() for t in helpers)


def test_the_scan_is_an_input_only_where_a_restart_checks_it():
    """`scan_depth2` is a flow+pose input where the finest level's restart runs (on more than one
    level) and the check is on, or where the scan gate is on; a config that checks with the
    restart off (what `--set pt_fine_restart=0` makes of the bundled model) is valid and takes no
    scan. The classical stage reads it for the restart's check or the gate, not for the judge
    between the two poses."""
    from types import SimpleNamespace

    from export.stages import solver_input_names
    from models.config import D3LVOConfig

    def takes_scan(**kw) -> bool:
        return "scan_depth2" in solver_input_names(SimpleNamespace(cfg=D3LVOConfig.small(pose_head="points", **kw)))

    assert takes_scan(pt_fine_restart=0.001, pt_restart_depth=0.5)
    assert not takes_scan(pt_fine_restart=0.0, pt_restart_depth=0.5)
    assert not takes_scan(pt_fine_restart=0.001, pt_restart_depth=0.0)
    assert not takes_scan(pt_fine_restart=0.001, pt_restart_depth=0.5, pt_iters=(15,))
    assert takes_scan(pt_fine_restart=0.0, pt_restart_depth=0.0, pt_scan_gate=0.05)  # the gate alone reads it
    from export.stages import classical_input_names

    def classical_takes_scan(**kw) -> bool:
        model = SimpleNamespace(cfg=D3LVOConfig.small(pose_head="points", pt_select=0.005, **kw))
        return "scan_depth2" in classical_input_names(model)

    assert classical_takes_scan(pt_fine_restart=0.001, pt_restart_depth=0.5)
    assert classical_takes_scan(pt_fine_restart=0.001, pt_restart_depth=0.0, pt_scan_gate=0.05)
    assert not classical_takes_scan(pt_fine_restart=0.001, pt_restart_depth=0.0, pt_select_scan_pass=0.7)
    assert DirectConfig.of_model(D3LVOConfig.small(pose_head="points", pt_fine_restart=0.001,
                                                   pt_restart_depth=0.5).to_dict()).restart_depth == 0.5


# pt_select pair by pair in a batch, with pt_refine 2 (whose steps run on the same doubled rows the
# select alone runs on): test_rotation_gate_in_the_exported_graphs_pair_by_pair
def test_dynamic_batch_solves_each_pair_as_alone(points_model):
    """With --dynamic-batch the solver's Loops run while any pair of the batch still moves: a batch
    of two pairs (different start motions, so their levels stop at different blocks) gives each
    pair the pose it gets alone, the fixture's finest-level restart from the start included. Each
    pair solved twice (`pt_select`: weighted and classical, batch rows 2i, 2i + 1 on pair i's
    images), with the refinement's check (`pt_refine`), and pairs that keep different solves:
    `test_rotation_gate_in_the_exported_graphs_pair_by_pair`."""
    import onnxruntime as ort

    from export.onnx_export import _sample_inputs
    from export.stages import flowpose_input_names
    from models.checkpoint import build_model, load_checkpoint

    ck, graphs = points_model  # exported with a dynamic batch
    model = build_model(load_checkpoint(ck))
    assert (model.cfg.pt_select, model.cfg.pt_refine) == (0.0, 0)  # one solve per pair
    names = flowpose_input_names(model)
    one = {n: t.numpy() for n, t in zip(names, _sample_inputs(model, model.cfg.height, model.cfg.width)["flowpose"])}
    other = dict(one, init_pose=make_se3(axis_angle_to_rot([0.0, 0.02, 0.0]), [0.1, 0.0, 1.0])[None].astype(np.float32),
                 **{n: np.roll(one[n], 1, -1) for n in names if n.startswith(("stack2_p", "image1_p"))})  # other frames
    for graph in ("flowpose.onnx", "flowpose.onnxruntime.onnx"):  # GridSample's and onnxruntime's
        sess = ort.InferenceSession(str(graphs / graph), providers=["CPUExecutionProvider"])
        alone = [sess.run(["matrix"], feeds)[0][0] for feeds in (one, other)]
        both = sess.run(["matrix"], {n: np.concatenate([one[n], other[n]]) for n in names})[0]
        assert np.abs(alone[0] - alone[1]).max() > 1e-3  # two different problems
        np.testing.assert_allclose(both, np.stack(alone), atol=1e-5)


def test_each_engines_graph_loops_over_its_own_steps(points_model):
    """The solver's Loop bodies follow their graph's layout: OpenVINO's samples with GridSample and
    eliminates (it cannot convert Det), onnxruntime's gathers pixel rows and takes one Det; every level's
    Loop in a graph runs the same kind of body. The export reuses a body exported before only
    where everything that shapes it matches, the layout included (`export/solver_loop.py`)."""
    from export.onnx_export import all_nodes

    _, onnx_dir = points_model
    want = {"flowpose.onnx": ({"GridSample"}, {"Det"}), "flowpose.onnxruntime.onnx": ({"Det"}, {"GridSample"})}
    for graph, (present, absent) in want.items():
        loops = [n for n in onnx.load(str(onnx_dir / graph)).graph.node if n.op_type == "Loop"]
        assert len(loops) == 3, graph  # one per pyramid level
        for loop in loops:
            ops = {n.op_type for n in all_nodes(loop.attribute[0].g)}
            assert present <= ops and not ops & absent, (graph, loop.name, sorted(ops & (present | absent)))


def test_rotation_gate_in_the_exported_graphs_pair_by_pair(points_model, tmp_path):
    """`pt_select_rotation` as exported, in a dynamic batch of two pairs, against torch, with
    the refinement's check of the solved poses (`pt_refine` 2) and the fixture's finest-level
    restart: each pair is solved twice, on batch rows 2i, 2i + 1 reading pair i's images. With a
    confidence that varies strongly over the image (the fixture's last confidence layer redrawn at
    std 3), torch's weighted and classical poses of the two pairs differ in rotation by two
    different small angles (`geometry.rotation_angle_precise`, float64), and the gain alone keeps
    both weighted poses.
    With the rotation threshold between the two angles, the exported graphs keep the weighted pose
    of the pair whose rotations differ more and the classical pose of the other, alone and in the
    batch, in both graphs, and the next start is the weighted pose either way. The classical solve
    exported alone (`classical`) gives torch's classical poses, and the flow+pose graph that takes
    it (`flowpose_weighted`) every output of the batched graph, to the bit. A cap on the share of
    distrusted points (`pt_select_share`) between the two pairs' shares keeps the classical pose of
    the pair whose network distrusts more, in torch and in that exported graph."""

    import onnxruntime as ort

    from export.onnx_export import DEFAULT_OPSET, _export_one, _sample_inputs
    from export.stages import ClassicalStage, FlowPoseStage, flowpose_input_names
    from models.checkpoint import build_model, load_checkpoint
    from models.d3lvo import D3LVO
    from models.sampling import gathered

    fixture = build_model(load_checkpoint(points_model[0]))
    # without the restart's scan check: the choice between the weighted and the classical pose alone
    # two pyramid levels: the choice between the poses is what is tested; each level is graph to export
    model = D3LVO(replace(fixture.cfg, pt_restart_depth=0.0, pt_iters=(6, 6))).eval()
    model.load_state_dict(fixture.state_dict())
    torch.manual_seed(1)
    with torch.no_grad():
        model.point_pose.moving.net[-1].weight.normal_(std=3.0)
        model.point_pose.moving.net[-1].bias.zero_()
    names = flowpose_input_names(model)
    one = {n: t.numpy() for n, t in zip(names, _sample_inputs(model, model.cfg.height, model.cfg.width)["flowpose"])}
    other = dict(one, init_pose=make_se3(axis_angle_to_rot([0.0, 0.02, 0.0]), [0.1, 0.0, 1.0])[None].astype(np.float32),
                 **{n: np.roll(one[n], 1, -1) for n in names if n.startswith(("stack2_p", "image1_p"))})
    batch = {n: np.concatenate([one[n], other[n]]) for n in names}

    def torch_poses(weights=False, **solver):  # (kept, next start) of both pairs, the same weights under these settings
        m = D3LVO(replace(model.cfg, pt_refine=2, **solver)).eval()
        m.load_state_dict(model.state_dict())
        stage = FlowPoseStage(m)
        with torch.no_grad():
            out = dict(zip(stage.output_names, stage(*(torch.from_numpy(batch[n]) for n in names))))
        poses = out["matrix"].double().numpy(), out["start_next"].double().numpy()
        return (*poses, out["point_weights"]) if weights else poses

    classical, weighted = torch_poses(pt_select=0.999)
    kept, _, weight = torch_poses(pt_select=1e-6, weights=True)
    np.testing.assert_allclose(kept, weighted, atol=1e-12)  # the gain alone keeps both weighted poses
    # `pt_select_share` between the two pairs' shares of distrusted points: the pair whose network
    # distrusts more of its points keeps the classical pose, the other its weighted one
    from models.pose_points import distrusted_share

    shares = distrusted_share(weight, torch.from_numpy(batch["point_mask1"])).numpy()
    assert 0 < shares.min() < shares.max() < 1, shares
    kept, _ = torch_poses(pt_select=1e-6, pt_select_share=float(shares.mean()))
    np.testing.assert_allclose(kept, np.stack([weighted[i] if shares[i] < shares.mean() else classical[i]
                                               for i in range(2)]), atol=1e-12)
    assert (np.abs(weighted - classical).max(axis=(1, 2)) > 1e-4).all()  # far beyond the tolerance below
    angles = np.degrees(rotation_angle_precise(classical[:, :3, :3].transpose(0, 2, 1) @ weighted[:, :3, :3]))
    assert angles.min() > 1e-3 and angles.max() > 1.5 * angles.min(), angles
    gate = {"pt_select": 1e-6, "pt_select_rotation": float(np.sqrt(angles.prod())), "pt_refine": 2,
            "pt_restart_depth": 0.0}
    # the three graphs the choice runs in, each in both forms (GridSample's and onnxruntime's Gathers),
    # exported as `export_checkpoint` does; completion and encoder play no part
    gated = D3LVO(replace(model.cfg, **gate)).eval()
    gated.load_state_dict(model.state_dict())
    (tmp_path / "gate").mkdir()
    sample = _sample_inputs(gated, gated.cfg.height, gated.cfg.width)
    for name, stage in (("flowpose", FlowPoseStage(gated)), ("classical", ClassicalStage(gated)),
                        ("flowpose_weighted", FlowPoseStage(gated, weighted=True))):
        for suffix, gathering in ((".onnx", False), (".onnxruntime.onnx", True)):
            with gathered(gathering):
                _export_one(stage.eval(), sample[name], tmp_path / "gate" / f"{name}{suffix}", DEFAULT_OPSET, dynamic_batch=True)
    want = np.stack([weighted[i] if angles[i] > angles.min() else classical[i] for i in range(2)])
    for graph in ("flowpose.onnx", "flowpose.onnxruntime.onnx"):  # GridSample's and onnxruntime's
        sess = ort.InferenceSession(str(tmp_path / "gate" / graph), providers=["CPUExecutionProvider"])
        # the classical mode solved apart (`classical`), its pose then given to the flow+pose graph
        # that takes it (`flowpose_weighted`): every output as the batched graph's, to the bit
        split = graph.replace("flowpose", "{}")
        alone = ort.InferenceSession(str(tmp_path / "gate" / split.format("classical")),
                                     providers=["CPUExecutionProvider"])
        given = ort.InferenceSession(str(tmp_path / "gate" / split.format("flowpose_weighted")),
                                     providers=["CPUExecutionProvider"])
        for feeds, rows in ((batch, slice(0, 2)), (one, slice(0, 1)), (other, slice(1, 2))):
            kept, start = sess.run(["matrix", "start_next"], feeds)
            np.testing.assert_allclose(kept, want[rows], atol=1e-5)
            np.testing.assert_allclose(start, weighted[rows], atol=1e-5)
            pose = alone.run(None, {i.name: feeds[i.name] for i in alone.get_inputs()})[0]
            np.testing.assert_allclose(pose, classical[rows], atol=1e-5)
            both = given.run(None, {**feeds, "classical_pose": pose})
            for name, a, b in zip([o.name for o in sess.get_outputs()], sess.run(None, feeds), both):
                np.testing.assert_array_equal(a, b, err_msg=f"{split.format('flowpose_weighted')}: {name}")
    # the cap exported: the flow+pose graph that takes the classical pose, with the gain alone and
    # `pt_select_share` between the pairs' shares, keeps the weighted pose of the pair whose network
    # distrusts less and the classical pose of the other (torch's choice above)
    cap = D3LVO(replace(model.cfg, pt_refine=2, pt_select=1e-6, pt_select_share=float(shares.mean()))).eval()
    cap.load_state_dict(model.state_dict())
    stage = FlowPoseStage(cap, weighted=True).eval()
    _export_one(stage, _sample_inputs(cap, cap.cfg.height, cap.cfg.width)["flowpose_weighted"], tmp_path / "cap.onnx",
                DEFAULT_OPSET, dynamic_batch=True)
    capped = ort.InferenceSession(str(tmp_path / "cap.onnx"), providers=["CPUExecutionProvider"])
    kept = capped.run(["matrix"], {**batch, "classical_pose": classical.astype(np.float32)})[0]
    np.testing.assert_allclose(kept, np.stack([weighted[i] if shares[i] < shares.mean() else classical[i]
                                               for i in range(2)]), atol=1e-5)


@pytest.mark.parametrize("which", ["scan_judge_model", "bundled"])
def test_runtime_solves_the_classical_mode_beside_and_writes_the_batched_poses(which, small_synth, tmp_path, request):
    """A model that chooses between its weighted and its classical pose (`pt_select`,
    `scan_judge_model`) is exported with the classical solve as a stage of its own. On two threads
    the runtime opens it and the flow+pose graph that takes its pose, not the batched graph, solves
    it on its helper thread while completion and encoder run (its time in `last_timing.beside`,
    outside the frame's total), and writes the poses the batched graph gives (the switch off), to
    the bit on onnxruntime; on one thread it runs the batched graph. The same for the bundled model,
    whose classical solve starts where the weighted one does (the fixture's from its own pose)."""
    from d3lvo_deploy.backends import SessionConfig
    from d3lvo_deploy.manifest import load_manifest
    from d3lvo_deploy.odometry import Odometry

    from d3lvo_deploy.bundled import bundled_model_dir

    model_dir = bundled_model_dir() if which == "bundled" else request.getfixturevalue(which)[1]
    assert {"classical", "flowpose_weighted"} <= set(load_manifest(model_dir)["stages"])
    import threading

    seq = KittiSequence.open(small_synth)
    poses = {}
    for name, sc in {"beside": SessionConfig(threads=2), "batched": SessionConfig(threads=2, classical_beside=False),
                     "one thread": SessionConfig(threads=1)}.items():
        odo = Odometry(model_dir, seq.calib, sc)
        started, overlapped = threading.Event(), []
        if name == "beside":  # completion waits (up to 10 s) for the pair's classical solve to start
            solve, complete = odo.model.solve_classical, odo.model.complete
            odo.model.solve_classical = lambda inputs: (started.set(), solve(inputs))[1]

            def completing(*a):
                if odo._prev is not None:
                    overlapped.append(started.wait(10.0))
                    started.clear()
                return complete(*a)

            odo.model.complete = completing
        poses[name] = np.array([odo.step(seq.image(i), seq.scan(i)) for i in range(4)])
        if name == "beside":
            assert set(odo.model.sessions) == {"completion", "encoder", "classical", "flowpose_weighted"}
            assert odo.last_timing.beside["classical"] > 0 and "classical" not in odo.last_timing.ms
            assert overlapped == [True] * 3  # each pair's solve ran while its completion did
        else:
            assert set(odo.model.sessions) == {"completion", "encoder", "flowpose"} and not odo.last_timing.beside
    assert np.linalg.norm(poses["batched"][-1][:3, 3]) > 0.1  # it moved
    np.testing.assert_array_equal(poses["beside"], poses["batched"])
    np.testing.assert_allclose(poses["one thread"], poses["batched"], atol=1e-5)
    # a run's latencies: the solve beside in its own row, the frame's total the stages it waited for
    from d3lvo_deploy.odometry import BESIDE_ROW, STAGES
    from d3lvo_deploy.pipeline import RunConfig, run_sequence

    lat = run_sequence(seq, model_dir, RunConfig(out=tmp_path / "p.txt", end=4), SessionConfig(threads=2)).latencies_ms
    assert len(lat[BESIDE_ROW]) == 3  # the pairs
    frames = np.array([lat[k] for k in (*STAGES, "read")]).sum(0)
    np.testing.assert_allclose(lat["total"], frames)


def test_direct_method_is_the_models_classical_mode(points_model):
    """`--method direct` takes the point selection and solver settings of the model it stands for."""
    from d3lvo_deploy.manifest import load_manifest

    cfg = load_manifest(points_model[1])["model_config"]
    dc = DirectConfig.of_model({**cfg, "pt_iters": [3, 2], "pt_capacity": 999, "pt_min_gradient": 0.05,
                                "pt_stop": 3e-5, "pt_damping": 7e-3})
    assert dc.iterations == (3, 2) and dc.levels == 2
    assert dc.points.capacity == 999 and dc.points.min_gradient == 0.05
    assert dc.stop_step == 3e-5 and dc.damping == 7e-3
    assert DirectConfig.of_model(cfg).iterations == (6, 6, 6)  # the fixture's
    assert DirectConfig.of_model(cfg).fine_restart == 0.001 and DirectConfig.of_model(
        {**cfg, "pt_fine_restart": 0.0}).fine_restart == 0.0
    from models.config import D3LVOConfig

    defaults = D3LVOConfig.small(pose_head="points").to_dict()
    assert DirectConfig.of_model(defaults) == DirectConfig()  # the defaults agree on both sides


def test_export_set_reaches_the_graph(points_model, small_synth, tmp_path):
    """`d3lvo export --set` changes the exported solver, not only the manifest: a median (one
    TopK) at every pt_scale_every-th step of a level, so the fixture's (6, 6, 6) with the default
    3 (steps 0 and 3) gives 6 TopK nodes, its finest-level restart two more (the two poses'
    robust scales in `consensus_gain`; the restart's steps run in the same batch) and the restart's
    check against frame t's scan one (`lidar_depth_error`'s median, both poses in one batch);
    pt_iters=3,2 with pt_scale_every=1 and pt_fine_restart=0 gives 5, and without the restart the
    graph takes no scan; the point list is pt_capacity long, and
    with pt_median_stride=4 the steps' medians sort every fourth point (a TopK of 512 / 4 / 2 + 1).
    A Loop's TopKs count once per trip it may take (its trip-count input). That graph, fed by the
    torch-free runtime without a scan, gives the trajectory of torch under the same settings."""
    from typer.testing import CliRunner

    from cli.main import app
    from d3lvo_deploy.manifest import load_manifest
    from export.flops import loop_trips

    def topks(g):
        return sum(loop_trips(g, n.input[0]) * topks(n.attribute[0].g) if n.op_type == "Loop" else n.op_type == "TopK"
                   for n in g.node)

    def topk_and_capacity(folder):
        g = onnx.load(str(folder / "flowpose.onnx")).graph
        points = next(i for i in g.input if i.name == "points1")
        return topks(g), points.type.tensor_type.shape.dim[1].dim_value

    def loop_topk_lengths(folder):
        """The k of every TopK in the Loops' steps: a median's partial sort of N // 2 + 1."""
        ks = set()
        for n in onnx.load(str(folder / "flowpose.onnx")).graph.node:
            if n.op_type == "Loop":
                body = n.attribute[0].g
                consts = {c.output[0]: onnx.numpy_helper.to_array(c.attribute[0].t) for c in body.node
                          if c.op_type == "Constant"}
                ks |= {int(consts[t.input[1]][0]) for t in body.node if t.op_type == "TopK"}
        return ks

    ck, default_dir = points_model
    assert topk_and_capacity(default_dir) == (6 + 2 + 1, 2048)
    r = CliRunner().invoke(app, ["export", "--ckpt", str(ck), "--out", str(tmp_path / "o"), "--set", "pt_iters=3,2",
                                 "--set", "pt_capacity=512", "--set", "pt_stop=3e-5", "--set", "pt_scale_every=1",
                                 "--set", "pt_fine_restart=0", "--set", "pt_median_stride=4"])
    assert r.exit_code == 0, r.output
    assert topk_and_capacity(tmp_path / "o") == (5, 512)
    assert "scan_depth2" not in [i["name"] for i in load_manifest(tmp_path / "o")["stages"]["flowpose"]["inputs"]]
    m = load_manifest(tmp_path / "o")["model_config"]
    assert (m["pt_iters"], m["pt_capacity"], m["pt_stop"], m["pt_scale_every"], m["pt_fine_restart"]) == \
        ([3, 2], 512, 3e-5, 1, 0.0)
    assert loop_topk_lengths(default_dir) == {2048 // 2 + 1}
    assert loop_topk_lengths(tmp_path / "o") == {512 // 4 // 2 + 1} and m["pt_median_stride"] == 4
    from d3lvo_deploy.pipeline import RunConfig, run_sequence
    from d3lvo_deploy.poses import read_poses
    from models.checkpoint import build_model, load_checkpoint
    from models.config import D3LVOConfig
    from models.predict import predict_sequence

    torch_traj = predict_sequence(build_model({**load_checkpoint(ck), "config": D3LVOConfig.from_dict(m)}), small_synth)
    run_sequence(KittiSequence.open(small_synth), tmp_path / "o", RunConfig(out=tmp_path / "p.txt"))
    np.testing.assert_allclose(read_poses(tmp_path / "p.txt").poses[:, :3, 3], torch_traj[:, :3, 3], atol=1e-4)
    # parity holds the export to its checkpoint under the export's own solver settings
    from export.parity import run_parity

    rep = run_parity(ck, tmp_path / "o", small_synth, frames=2)
    assert rep.passed, rep.to_dict()


def test_no_points_no_motion_beyond_the_start():
    """A pair without points (an empty scan, a textureless frame) stops every level at once, as the
    numpy tracker's `break` does: the start motion comes back, finite."""
    A = make_se3(axis_angle_to_rot([0.0, 0.01, 0.0]), [0.05, 0.0, 0.6])
    calib, _, (g0, g1, pts, mask), _ = _plane_inputs(A)
    init = make_se3(np.eye(3), [0.0, 0.0, 0.7])
    out = solve(*image_pyramids(g0, g1, 3), pts, mask * 0, _k(calib.K2), _t(init)[None], SolverSettings())[-1][0].numpy()
    assert np.allclose(out, init, atol=1e-12)


def test_runtime_steps_past_an_empty_scan(points_model, small_synth):
    """The runtime's documented fallback for a scan without points: a pose, not an error."""
    from d3lvo_deploy.odometry import Odometry

    seq = KittiSequence.open(small_synth)
    odo = Odometry(points_model[1], seq.calib)
    odo.step(seq.image(0), np.zeros((0, 4), np.float32))
    with pytest.warns(UserWarning, match="no LiDAR points"):
        pose = odo.step(seq.image(1), np.zeros((0, 4), np.float32))
    assert np.all(np.isfinite(pose))


def test_bad_solver_settings_are_one_clear_error():
    from d3lvo_deploy.errors import D3LVOInputError
    from cli.export_cmd import solver_settings
    from models.config import D3LVOConfig

    with pytest.raises(ValueError, match="pt_iters takes one step count per pyramid level"):
        D3LVOConfig.small(pose_head="points", **solver_settings(["pt_iters=15"]))
    with pytest.raises(ValueError, match="pt_gate must be in"):
        D3LVOConfig.small(pose_head="points", pt_gate=1.5)
    with pytest.raises(ValueError, match="pt_restart_depth must be in"):
        D3LVOConfig.small(pose_head="points", **solver_settings(["pt_restart_depth=2"]))
    for share in ("0", "1.5"):  # a cap of 0 would never keep the weighted pose: off is 1
        with pytest.raises(ValueError, match=r"pt_select_share must be a share in \(0, 1\] \(1: off\)"):
            D3LVOConfig.small(pose_head="points", **solver_settings([f"pt_select_share={share}"]))
    with pytest.raises(D3LVOInputError, match="solver settings only"):
        solver_settings(["height=10"])
    # numbers as Python writes them, negative ones too; a word for a number is refused by name
    assert solver_settings(["pt_stop=1E-6", "pt_gate=-0.5", "pt_iters=9,9,9", "pt_affine=True"]) == \
        {"pt_stop": 1e-6, "pt_gate": -0.5, "pt_iters": (9, 9, 9), "pt_affine": True}
    for bad, words in (("pt_stop=abc", "pt_stop takes a finite number"), ("pt_stop=nan", "pt_stop takes a finite"),
                       ("pt_iters=a,b", "pt_iters takes whole numbers separated by commas"),
                       ("gn_iters=2.5", "gn_iters takes a whole number"),
                       ("pt_affine=3", "pt_affine takes true or false"),
                       ("pt_classical_chain=yes", "pt_classical_chain takes true or false")):
        with pytest.raises(D3LVOInputError, match=words):
            solver_settings([bad])
    with pytest.raises(ValueError, match="pt_gate must be in"):
        D3LVOConfig.small(pose_head="points", **solver_settings(["pt_gate=-0.5"]))
    with pytest.raises(ValueError, match="pt_classical_chain must be true or false"):
        D3LVOConfig.small(pose_head="points", pt_classical_chain=1)
    with pytest.raises(ValueError, match="pt_classical_chain needs a point solver that also solves its classical"):
        D3LVOConfig.small(pose_head="points", pt_classical_chain=True)  # pt_select 0: no classical solve


def test_int8_export_keeps_the_point_solver_in_fp32(points_model, small_synth, tmp_path):
    """INT8 quantizes the convolution stages; the point solver's stage (its only Conv is the image
    pyramid the photometric residual reads) stays FP32, and the quantized folder runs."""
    from d3lvo_deploy.manifest import load_manifest
    from d3lvo_deploy.odometry import Odometry
    from export.quantize import quantize_folder

    m = quantize_folder(points_model[1], tmp_path / "int8", "int8", [small_synth])
    assert m["stages"]["flowpose"]["precision"] == "fp32" and m["stages"]["encoder"]["precision"] == "int8"
    # onnxruntime's own FP32 flow+pose graph comes along with the stage (load_manifest checks its hash)
    assert m["stages"]["flowpose"]["onnxruntime"] == load_manifest(points_model[1])["stages"]["flowpose"]["onnxruntime"]
    seq = KittiSequence.open(small_synth)
    odo = Odometry(tmp_path / "int8", seq.calib)
    poses = [odo.step(seq.image(i), seq.scan(i)) for i in range(3)]
    assert load_manifest(tmp_path / "int8")["stages"]["flowpose"]["precision"] == "fp32"
    assert np.linalg.norm(poses[-1][:3, 3]) > 0.5  # it moved, and finitely


def test_init_takes_matching_weights_and_refuses_a_foreign_checkpoint(tmp_path, small_synth):
    """--init copies every tensor whose name and shape fit (a point-head model from a cell-solver
    checkpoint keeps its encoder), and a checkpoint with nothing that fits is one clear error."""
    from conftest import make_checkpoint
    from d3lvo_deploy.errors import D3LVOInputError
    from models.config import D3LVOConfig
    from models.d3lvo import D3LVO
    from models.train import TrainConfig, load_matching, train

    cells = make_checkpoint(tmp_path / "cells.pt")
    model = D3LVO(D3LVOConfig.small(height=64, width=224, pose_head="points"))
    taken = load_matching(model, str(cells))
    theirs = torch.load(cells, weights_only=False)["model"]
    key = "encoder.rgb.0.0.0.weight"
    assert taken > 0 and torch.equal(model.state_dict()[key], theirs[key])
    from models.checkpoint import save_checkpoint

    cfg = D3LVOConfig.small(height=64, width=224, pose_head="points")
    other = tmp_path / "other.pt"  # a valid checkpoint file whose weights belong to something else
    save_checkpoint(other, torch.nn.Linear(3, 2), cfg, step=1)
    tc = TrainConfig(data=[str(small_synth)], out=str(tmp_path / "x.pt"), steps=1, init=str(other))
    with pytest.raises(D3LVOInputError, match="none of its weights fits"):
        train(cfg, tc)
    # a partial start is said, with the count load_matching took
    notes: list[str] = []
    train(cfg, TrainConfig(data=[str(small_synth)], out=str(tmp_path / "y.pt"), steps=1, batch_size=1, init=str(cells)),
          on_note=notes.append)
    assert notes == [f"--init {cells}: {taken} of the model's {len(model.state_dict())} tensors taken (name and shape "
                     "match); the rest start fresh"]


def test_pose_error_gradient_through_the_solver_blames_the_moved_points():
    """The solver is differentiable in the point weights: on the plane whose left half moved like
    another object, the gradient of the pose error raises the error with the moved points' weight
    and lowers it with the static ones': what a pose loss through the solver teaches the
    confidence."""
    A = make_se3(axis_angle_to_rot([0.0, 0.01, 0.0]), [0.05, 0.0, 0.6])
    calib, (img0, img1, _), (g0, g1, pts, mask), X = _plane_inputs(A)
    left = torch.as_tensor((calib.K2[0, 0] * X[:, 0] / X[:, 2] + calib.K2[0, 2]) < 310)
    moved = img1.copy()
    moved[:, :280] = np.roll(img1, 25, axis=1)[:, :280]
    g1m = _t(grey_image(moved))[None, None]
    weights = mask.clone().requires_grad_(True)
    M = solve(*image_pyramids(g0, g1m, 3), pts, weights, _k(calib.K2), _t(np.eye(4))[None], SolverSettings())[-1]
    err = ((M[0, :3, 3] - _t(A[:3, 3])) ** 2).sum()
    err.backward()
    g = weights.grad[0, : len(X)]
    assert float(g[left].mean()) > 0 > float(g[~left].mean()), (float(g[left].mean()), float(g[~left].mean()))


def test_training_with_a_pose_loss_through_the_solver(small_synth, tmp_path):
    """--solver-loss: samples carry the solver's inputs, eq. 11 is taken on the solver's poses,
    and flips and rotations (which the solver's camera images would not get) are refused."""
    from models.config import D3LVOConfig
    from models.data import AugmentConfig, PairDataset
    from models.loss import LossConfig
    from models.train import TrainConfig, train

    cfg = D3LVOConfig.small(height=64, width=224, pose_head="points")
    with pytest.raises(ValueError, match="flip and rotation_deg must be 0"):
        PairDataset([small_synth], cfg, augment=AugmentConfig(), solver=True)
    item = PairDataset([small_synth], cfg, augment=None, solver=True)[0]
    assert item["points1"].shape == (cfg.pt_capacity, 3) and item["image1"].ndim == 3
    tc = TrainConfig(data=[str(small_synth)], out=str(tmp_path / "s.pt"), steps=2, batch_size=2,
                     loss=LossConfig(solver_pose_weight=1.0))
    rec = train(cfg, tc)
    assert rec["pose_loss"] != 0.0 and "level2" in rec, rec
    off = train(cfg, TrainConfig(data=[str(small_synth)], out=str(tmp_path / "m.pt"), steps=2, batch_size=2))
    assert off["pose_loss"] == 0.0


def test_solver_samples_trace_under_torch_compile():
    """`d3lvo bench --torch-compile` compiles the point head: the image size must come from the
    Python shape there (dynamo gives `_shape_as_tensor` back as a torch.Size), and the export's
    graph still reads it from the tensor (the export tests above)."""
    rng = np.random.default_rng(0)
    img = _t(rng.uniform(0, 1, (1, 3, 20, 30)))
    uv = _t(rng.uniform(-2, 32, (1, 50, 2)))
    uv[0, 0] = torch.tensor([12.25, 7.5], dtype=D)  # inside: checked by hand below
    got = torch.compile(sample_at, backend="eager", fullgraph=True)(img, uv)
    torch.testing.assert_close(got, sample_at(img, uv))
    im = img[0, 0].numpy()
    ref = 0.5 * (0.75 * im[7, 12] + 0.25 * im[7, 13]) + 0.5 * (0.75 * im[8, 12] + 0.25 * im[8, 13])
    assert abs(float(got[0, 0, 0]) - ref) < 1e-9


class _Level(torch.nn.Module):
    """One level of the solver, `align_level`, as a graph of its own."""

    def __init__(self, iterations: int):
        super().__init__()
        self.iterations = iterations

    def forward(self, R, t, X, ref, stack, K, weight):
        from models.point_solver import align_level

        return align_level(R, t, X, ref, stack, K, weight, (weight > 0.5).float(), self.iterations, SolverSettings())


def test_the_exported_loop_is_the_steps_and_ends_when_the_level_stops(tmp_path, monkeypatch):
    """One level of 15 steps (5 blocks of 3) on the textured plane from a start 2 cm off: PyTorch
    breaks after the block in which the level stops, and gives what computing every block gives
    (a stopped level's steps are zero); the exported graph holds a standard Loop that gives the
    same pose on onnxruntime and runs as many blocks as PyTorch (its GridSamples counted in an
    onnxruntime profile), fewer than 5."""
    import json

    import onnxruntime as ort

    import models.point_solver as ps
    from export.solver_loop import splice_loops

    A = make_se3(axis_angle_to_rot([0.002, -0.004, 0.001]), [0.02, -0.01, 0.3])
    calib, _, (g0, g1, pts, mask), _ = _plane_inputs(A, capacity=2048)
    start = se3_inv(make_se3(axis_angle_to_rot([0.002, -0.004, 0.001]), [0.02, -0.01, 0.32]))
    K = _k(calib.K2).float()
    X = pts.float()
    args = (torch.tensor(start[None, :3, :3], dtype=torch.float32), torch.tensor(start[None, None, :3, 3], dtype=torch.float32),
            X, sample_at(g0.float(), project(X, K)[0])[:, 0], with_gradients(g1.float()), K, mask.float())
    level = _Level(15).eval()

    blocks = []
    steps = ps.gn_steps
    monkeypatch.setattr(ps, "gn_steps", lambda *a: blocks.append(1) or steps(*a))
    R, t = level(*args)
    ran = len(blocks)
    with monkeypatch.context() as m:
        m.setattr(torch.jit, "is_tracing", lambda: True)  # no break: every block computed
        R_all, t_all = level(*args)
    assert 1 < ran < 5 and len(blocks) == ran + 5
    assert torch.equal(R, R_all) and torch.equal(t, t_all)
    truth = se3_inv(A)
    assert np.abs(t[0, 0].numpy() - truth[:3, 3]).max() < 2e-3  # it converged, not merely stopped

    path = tmp_path / "level.onnx"
    names = ["R", "t", "X", "ref", "stack", "K", "weight"]
    torch.onnx.export(level, args, str(path), input_names=names, output_names=["R_out", "t_out"], opset_version=17,
                      dynamo=False)
    model = splice_loops(onnx.load(str(path)), 17, False)
    onnx.checker.check_model(model, full_check=True)
    assert [n.op_type for n in model.graph.node].count("Loop") == 1
    assert {o.domain for o in model.opset_import} <= {"", "ai.onnx"}
    onnx.save(model, str(path))
    so = ort.SessionOptions()
    so.enable_profiling, so.profile_file_prefix = True, str(tmp_path / "prof")
    sess = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    R_onnx, t_onnx = sess.run(None, {n: a.numpy() for n, a in zip(names, args)})
    events = json.loads(open(sess.end_profiling()).read())
    samples = sum(e.get("cat") == "Node" and e["name"].endswith("_kernel_time") and e["args"].get("op_name") == "GridSample"
                  for e in events)
    np.testing.assert_allclose(R_onnx, R.numpy(), atol=1e-5)
    np.testing.assert_allclose(t_onnx, t.numpy(), atol=1e-5)
    assert samples == 3 * ran


@pytest.mark.parametrize("stride", [1, 4])
def test_scan_gate_is_the_numpy_trackers(stride):
    """The graph's gate keeps the points the numpy tracker keeps on the hand-built case
    (`test_direct._gate_case`); on the real pair 11-12 with the bundled settings and the gate at
    0.05, the solve with every confidence 1 gives the numpy tracker's motion within 1e-6 m, and the
    gate moves that motion by more than that (it drops points there); also with the Huber median
    over every fourth point, which both count by place in the point list the gate thinned."""
    from d3lvo_deploy.direct import scan_gated
    from models.point_solver import scan_kept
    from test_direct import _gate_case

    prev, depth, forward = _gate_case()
    kept = scan_kept(_t(forward)[None], _t(prev.points)[None], _t(depth)[None, None], _k(prev.levels[0].K), 0.05)
    assert kept[0].tolist() == [1.0, 0.0, 1.0, 0.0]
    assert len(scan_gated(prev, depth, forward, 0.05).points) == 2
    cfg = DirectConfig(affine_brightness=True, fine_restart=0.001, restart_depth=0.5, scan_gate=0.05,
                       median_stride=stride)
    seq, init, prev, cur = _pair_11_12(cfg)
    want = track(prev, cur, init, cfg)
    ungated = track(prev, cur, init, replace(cfg, scan_gate=0.0))
    assert np.linalg.norm(want[:3, 3] - ungated[:3, 3]) > 1e-5
    pts, mask = pad_points(prev.points, cfg.points.capacity)
    images = [_t(grey_image(seq.image(i)))[None, None] for i in (11, 12)]
    got = solve(*image_pyramids(*images, 3), _t(pts), _t(mask), _k(seq.calib.K2), _t(init)[None],
                SolverSettings(cfg.iterations, affine=True, fine_restart=0.001, restart_depth=0.5, scan_gate=0.05,
                               median_stride=stride),
                depth2=_t(cur.depth)[None, None])[-1][0].numpy()
    assert np.abs(got[:3, 3] - want[:3, 3]).max() < 1e-6 and np.abs(got[:3, :3] - want[:3, :3]).max() < 1e-7
