"""The geometric pose head's solver against independent references: torch.linalg, matrix_exp,
the numpy geometry module, and known motions recovered from rendered features."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from d3lvo_deploy.geometry import rot_to_quat, skew
from models import gauss_newton as gn


def _rotation(w: torch.Tensor) -> torch.Tensor:
    """(1,3) float64 axis-angle -> (1,3,3) by the matrix exponential of its numpy cross-product matrix."""
    return torch.linalg.matrix_exp(torch.from_numpy(skew(w[0].numpy())))[None]


def test_spd_solve_matches_linalg_on_normal_equations_of_mixed_scale():
    """A solver step's 6x6 system: translation and rotation columns of very different scale
    (pixels per metre against pixels per radian), solved in float32 as the graph runs it."""
    g = torch.Generator().manual_seed(0)
    J = torch.randn(5, 200, 6, generator=g, dtype=torch.float64) * torch.tensor([1.0, 1.0, 0.1, 300.0, 300.0, 50.0],
                                                                                   dtype=torch.float64)
    H = J.transpose(1, 2) @ J
    b = torch.randn(5, 6, generator=g, dtype=torch.float64) * 100.0
    ref = torch.linalg.solve(H, b)
    np.testing.assert_allclose(gn.spd_solve(H, b), ref, rtol=1e-9, atol=1e-12)
    x32 = gn.spd_solve(H.float(), b.float()).double()
    assert float(((x32 - ref).abs() / ref.abs().clamp(min=1e-6)).max()) < 1e-3


def test_so3_exp_small_matches_so3_exp_within_a_steps_range():
    axis = torch.tensor([[0.3, -0.8, 0.52]], dtype=torch.float64)
    for angle in (0.0, 1e-4, 0.01, 0.02, 0.04):
        w = axis / axis.norm() * angle
        ref = _rotation(w)
        np.testing.assert_allclose(gn.so3_exp_small(w), ref, atol=1e-12)
        # float32, as exported: the series keeps a step's small angles exact to float precision
        np.testing.assert_allclose(gn.so3_exp_small(w.float()).double(), ref, atol=2e-7)


def test_matrix_to_pose_matches_numpy_quaternion():
    g = torch.Generator().manual_seed(1)
    for _ in range(5):
        w = torch.randn(1, 3, generator=g, dtype=torch.float64) * 0.3
        M = torch.eye(4, dtype=torch.float64)[None].clone()
        M[0, :3, :3] = _rotation(w)[0]
        M[0, :3, 3] = torch.tensor([0.1, -0.2, 1.5])
        p = gn.matrix_to_pose(M)[0].numpy()
        np.testing.assert_allclose(p[:3], [0.1, -0.2, 1.5])
        np.testing.assert_allclose(p[3:], rot_to_quat(M[0, :3, :3].numpy()), atol=1e-12)


def test_pixel_jacobian_matches_autograd_through_the_update():
    """d pi(exp(xi) X) / d xi at 0, against autograd through `update` and `project`."""
    X = torch.tensor([[[1.0, -0.5, 8.0], [-3.0, 1.0, 20.0]]], dtype=torch.float64)
    K = torch.tensor([[300.0, 310.0, 150.0, 40.0]], dtype=torch.float64)
    J = gn.pixel_jacobian(X, K, 4.0)
    xi = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    uv, _ = gn.project(gn.apply(gn.update(torch.eye(4, dtype=torch.float64)[None], xi), X), K, 4.0)
    for n in range(2):
        for k in range(2):
            (grad,) = torch.autograd.grad(uv[0, n, k], xi, retain_graph=True)
            np.testing.assert_allclose(J[0, n, k].numpy(), grad[0].numpy(), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("motion", ["forward", "turn"])
def test_gauss_newton_recovers_a_known_motion(motion):
    """Features of frame t are frame t-1's, moved by a known rigid motion (exact, through the
    same projection); Gauss-Newton from identity must find that motion."""
    h, w, scale = 44, 152, 4.0
    K = torch.tensor([[0.59 * 608, 0.59 * 608, 303.5, 87.5]], dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    # frame t's features: a smooth texture on frame t's grid; frame t-1's features: frame t's
    # sampled where frame t-1's cells land under the true motion, so the residual is exactly zero there
    f2 = torch.nn.functional.interpolate(torch.randn(1, 2, h // 4, w // 4, generator=g, dtype=torch.float64),
                                         size=(h, w), mode="bicubic", align_corners=True)
    v = torch.arange(h, dtype=torch.float64).view(1, 1, h, 1).expand(1, 1, h, w)
    depth = torch.where(v > h / 2, 40.0 / (v - h / 2 + 2.0), torch.full_like(v, 15.0))
    inv = 0.5 / depth
    true = torch.eye(4, dtype=torch.float64)[None].clone()
    if motion == "forward":
        true[0, :3, 3] = torch.tensor([0.05, -0.02, -0.8])  # M moves points toward the camera
    else:
        true[0, :3, :3] = _rotation(torch.tensor([[0.0, 0.02, 0.0]], dtype=torch.float64))[0]
        true[0, :3, 3] = torch.tensor([0.1, 0.0, -0.5])
    X, valid = gn.backproject(inv, K, scale, 0.5)
    uv, _ = gn.project(gn.apply(true, X), K, scale)
    f1 = gn.sample(f2, uv).reshape(1, 2, h, w)
    inside = ((uv[..., 0] >= 1) & (uv[..., 0] <= w - 2) & (uv[..., 1] >= 1) & (uv[..., 1] <= h - 2)).to(X.dtype)
    M = torch.eye(4, dtype=torch.float64)[None]
    for _ in range(14):  # from identity to 0.8 m: quadratic convergence sets in after ~9 steps
        Xt = gn.apply(M, X)
        uvt, front = gn.project(Xt, K, scale)
        gx, gy = gn.image_gradients(f2)
        s = gn.sample(torch.cat([f2, gx, gy], 1), uvt)
        r = (s[:, :2] - f1.reshape(1, 2, -1)).transpose(1, 2)
        G = torch.stack([s[:, 2:4], s[:, 4:6]], -1).transpose(1, 2)
        J = G @ gn.pixel_jacobian(Xt, K, scale)
        H, gg = gn.normal_equations(J, r, valid * inside * front)
        M = gn.update(M, gn.damped_step(H, gg, 1e-4, max_rot=0.05, max_trans=1.0))
    err = gn.invert(true) @ M
    assert float(err[0, :3, 3].norm()) < 1e-4  # m, from a 0.8 m motion
    angle = float(torch.arccos(((err[0, 0, 0] + err[0, 1, 1] + err[0, 2, 2] - 1) / 2).clamp(-1, 1)))
    assert np.degrees(angle) < 1e-3


def test_trust_region_caps_the_step():
    H = torch.eye(6, dtype=torch.float64)[None] * 1e-3
    g = torch.tensor([[10.0, 0, 0, 0, 0, -10.0]], dtype=torch.float64)
    xi = gn.damped_step(H, g, 0.0, max_rot=0.02, max_trans=0.3)
    assert float(xi[0, :3].norm()) <= 0.3 + 1e-12 and float(xi[0, 3:].norm()) <= 0.02 + 1e-12
    # the direction of the undamped Newton step is kept
    np.testing.assert_allclose((xi / xi.norm()).numpy(), (-g / g.norm()).numpy(), atol=1e-12)


def test_feature_normal_equations_equal_the_full_jacobian():
    g = torch.Generator().manual_seed(5)
    b, c, n = 2, 3, 40
    Jp = torch.randn(b, n, 2, 6, generator=g, dtype=torch.float64)
    r, gu, gv = (torch.randn(b, c, n, generator=g, dtype=torch.float64) for _ in range(3))
    w = torch.rand(b, n, generator=g, dtype=torch.float64)
    G = torch.stack([gu, gv], -1).transpose(1, 2)  # (B,N,C,2)
    H_ref, g_ref = gn.normal_equations(G @ Jp, r.transpose(1, 2), w)
    H, gg = gn.feature_normal_equations(Jp, r, gu, gv, w)
    np.testing.assert_allclose(H, H_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(gg, g_ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("pool", ["stride", "nearest"])
def test_lidar_cells_by_hand(pool):
    """Returns at input pixels (row 5, col 7) and (8, 8), inverse depths 0.3 and 0.5. "stride" keeps
    a return only on a cell's own pixel s*i; "nearest" gives each cell the closest return (largest
    inverse depth) within s/2 pixels of s*i, so a return between two cells counts for both."""
    from models.config import D3LVOConfig
    from models.d3lvo import D3LVO

    cfg = D3LVOConfig.small(height=64, width=224, gn_lidar_pool=pool)
    x = torch.zeros(1, 1, 64, 224)
    x[0, 0, 5, 7], x[0, 0, 8, 8] = 0.3, 0.5
    levels = D3LVO(cfg).lidar_levels(x)
    cells = [None if a is None else {tuple(ij): round(float(a[0, 0][tuple(ij)]), 3) for ij in torch.nonzero(a[0, 0]).tolist()}
             for a in levels]
    if pool == "stride":  # s = 2, 4, 8, 16: only (8, 8) lies on a cell's pixel, at s = 2, 4, 8
        assert cells[:3] == [{(4, 4): 0.5}, {(2, 2): 0.5}, {(1, 1): 0.5}]
        assert cells[3] == {}
    else:
        # s = 2: (5, 7) is within 1 pixel of rows 4, 6 and cols 6, 8 -> cells (2..3, 3..4); (8, 8) -> (4, 4)
        assert cells[0] == {(2, 3): 0.3, (2, 4): 0.3, (3, 3): 0.3, (3, 4): 0.3, (4, 4): 0.5}
        # s = 4, cell (i, j) sees rows 4i-2..4i+2 and cols 4j-2..4j+2: (5, 7) -> (1, 2), (8, 8) -> (2, 2)
        assert cells[1] == {(1, 2): 0.3, (2, 2): 0.5}
        assert cells[2] == {(1, 1): 0.5}  # s = 8: both within 4 px of (8, 8); the closer return wins
        # s = 16: (8, 8) is on the border of four cells' windows and the closer return in each
        assert cells[3] == {(0, 0): 0.5, (0, 1): 0.5, (1, 0): 0.5, (1, 1): 0.5}
