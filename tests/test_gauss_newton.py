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


@pytest.mark.parametrize("solve", [gn.scaled_solve, gn.cramer_solve], ids=["gauss_jordan", "cramer"])
def test_scaled_solve_matches_linalg_on_normal_equations_of_mixed_scale(solve):
    """A solver step's 6x6 system: translation and rotation columns of very different scale
    (pixels per metre against pixels per radian), solved in float32 as the graph runs it; by
    elimination (OpenVINO's graph) and by Cramer's rule (onnxruntime's)."""
    g = torch.Generator().manual_seed(0)
    J = torch.randn(5, 200, 6, generator=g, dtype=torch.float64) * torch.tensor([1.0, 1.0, 0.1, 300.0, 300.0, 50.0],
                                                                                   dtype=torch.float64)
    H = J.transpose(1, 2) @ J
    b = torch.randn(5, 6, 1, generator=g, dtype=torch.float64) * 100.0
    diag = torch.diagonal(H, dim1=1, dim2=2)
    ref = torch.linalg.solve(H + torch.diag_embed(0.5 * diag), b)  # Levenberg-Marquardt, lambda 0.5
    damped = (1.5 * diag).unsqueeze(-1)
    np.testing.assert_allclose(solve(torch.cat([H, b], -1), damped), ref, rtol=1e-9, atol=1e-12)
    x32 = solve(torch.cat([H, b], -1).float(), damped.float()).double()
    assert float(((x32 - ref).abs() / ref.abs().clamp(min=1e-6)).max()) < 1e-3
    # no points: H = 0 and b = 0 solve to 0, not NaN
    assert torch.equal(solve(torch.zeros(1, 6, 7), torch.full((1, 6, 1), 1e-12)), torch.zeros(1, 6, 1))


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


def _hat(w: torch.Tensor) -> torch.Tensor:
    o = w[0] * 0
    return torch.stack([torch.stack([o, -w[2], w[1]]), torch.stack([w[2], o, -w[0]]), torch.stack([-w[1], w[0], o])])


def _scene(h: int = 44, w: int = 152, channels: int = 2, seed: int = 3, returns: float = 1.0):
    """Smooth random features on a level grid, a road-like depth (near at the bottom, a wall
    above) with a return on this share of the cells, KITTI-like intrinsics in the level's cells."""
    g = torch.Generator().manual_seed(seed)
    f2 = torch.nn.functional.interpolate(torch.randn(1, channels, h // 4, w // 4, generator=g, dtype=torch.float64),
                                         size=(h, w), mode="bicubic", align_corners=True)
    v = torch.arange(h, dtype=torch.float64).view(1, 1, h, 1).expand(1, 1, h, w)
    depth = torch.where(v > h / 2, 40.0 / (v - h / 2 + 2.0), torch.full_like(v, 15.0))
    hit = (torch.rand(1, 1, h, w, generator=g, dtype=torch.float64) < returns).to(torch.float64)
    K = torch.tensor([[0.59 * w, 0.59 * w, (w - 1) / 2, (h - 1) / 2]], dtype=torch.float64)
    X, valid = gn.backproject(0.5 / depth * hit, K, 1.0, 0.5)
    return f2, X, valid, K


def _reference_step(M, X, f1, f2, weight, K, huber, damping, max_rot, max_trans):
    """One Levenberg-Marquardt step written from its definition: the full (N, C, 6) Jacobian of
    the residuals f2(pi(exp(xi) M X)) - f1, with the pixel Jacobian by autograd through the
    projection and the image gradients by np.gradient (central inside, one-sided at the border),
    sampled bilinearly; Huber weights on the channels' RMS residual; solved by torch.linalg."""
    _, c, h, w = f2.shape
    fx, fy, cx, cy = K[0]
    Xt0 = X[0] @ M[0, :3, :3].T + M[0, :3, 3]

    def pixels(xi):
        Xt = Xt0 @ torch.linalg.matrix_exp(_hat(xi[3:])).T + xi[:3]
        return torch.stack([fx * Xt[:, 0] / Xt[:, 2] + cx, fy * Xt[:, 1] / Xt[:, 2] + cy], -1)

    xi0 = torch.zeros(6, dtype=X.dtype)
    # forward mode: 6 inputs, 2N outputs (reverse mode would take one backward pass per output)
    Jp = torch.autograd.functional.jacobian(pixels, xi0, vectorize=True, strategy="forward-mode")  # (N,2,6)
    uv = pixels(xi0)
    gu = torch.from_numpy(np.gradient(f2[0].numpy(), axis=2))[None]
    gv = torch.from_numpy(np.gradient(f2[0].numpy(), axis=1))[None]
    s = gn.sample(torch.cat([f2, gu, gv], 1), uv[None])[0]  # (3C,N)
    r, su, sv = s[:c] - f1, s[c:2 * c], s[2 * c:]
    J = su[..., None] * Jp[None, :, 0] + sv[..., None] * Jp[None, :, 1]  # (C,N,6)
    u, v = uv[:, 0], uv[:, 1]
    inside = torch.stack([u, w - 1 - u, v, h - 1 - v]).amin(0).clamp(0, 1)
    rms = (r * r).mean(0).sqrt()
    wgt = weight[0] * inside * (Xt0[:, 2] > 0.1) * torch.where(rms <= huber, torch.ones_like(rms), huber / rms)
    H = torch.einsum("n,cni,cnj->ij", wgt, J, J)
    g = torch.einsum("n,cni,cn->i", wgt, J, r)
    diag = torch.diagonal(H)
    xi = -torch.linalg.solve(H + torch.diag(damping * diag + 1e-4 * diag.mean() + 1e-6), g)
    xi = xi * min(1.0, max_trans / float(xi[:3].norm()), max_rot / float(xi[3:].norm()))
    dR = torch.linalg.matrix_exp(_hat(xi[3:]))
    out = M.clone()
    out[0, :3, :3] = dR @ M[0, :3, :3]
    out[0, :3, 3] = dR @ M[0, :3, 3] + xi[:3]
    return out, xi


@pytest.mark.parametrize("limits", [(1.0, 10.0), (0.002, 0.01)], ids=["free", "trust-region"])
def test_a_step_is_levenberg_marquardt_on_the_full_jacobian(limits):
    """`feature_align`'s one-MatMul normal equations against the step written from its definition,
    on three channels, with a confidence, points behind the border and Huber-downweighted ones;
    with tight limits, the trust region shrinks the step, keeping its direction."""
    max_rot, max_trans = limits
    f2, X, valid, K = _scene(channels=3, returns=0.2)
    h, w = f2.shape[-2:]
    M = torch.eye(4, dtype=torch.float64)[None].clone()
    M[0, :3, :3] = _rotation(torch.tensor([[0.004, -0.03, 0.002]], dtype=torch.float64))[0]
    M[0, :3, 3] = torch.tensor([0.08, -0.02, -0.6])
    g = torch.Generator().manual_seed(7)
    f1 = gn.sample(f2, gn.project(gn.apply(M, X), K, 1.0)[0])[0] + 0.05 * torch.randn(3, h * w, generator=g,
                                                                                       dtype=torch.float64)
    start = torch.eye(4, dtype=torch.float64)[None]
    weight = valid * torch.rand(1, h * w, generator=g, dtype=torch.float64) * 2
    gx, gy = gn.image_gradients(f2)
    got = gn.feature_align(start, X, torch.cat([f2, gx, gy], 1), f1[None], weight, K, 1, 0.1, 1e-3,
                           max_rot=max_rot, max_trans=max_trans)
    ref, xi = _reference_step(start, X, f1, f2, weight, K, 0.1, 1e-3, max_rot, max_trans)
    np.testing.assert_allclose(got.numpy(), ref.numpy(), rtol=0, atol=1e-11)
    capped = abs(float(xi[:3].norm()) - max_trans) < 1e-12 or abs(float(xi[3:].norm()) - max_rot) < 1e-12
    assert capped == (limits == (0.002, 0.01))


@pytest.mark.parametrize("motion", ["forward", "turn"])
def test_gauss_newton_recovers_a_known_motion(motion):
    """Features of frame t are frame t-1's, moved by a known rigid motion (exact, through the
    same projection); Gauss-Newton from identity must find that motion."""
    f2, X, valid, K = _scene()
    h, w = f2.shape[-2:]
    true = torch.eye(4, dtype=torch.float64)[None].clone()
    if motion == "forward":
        true[0, :3, 3] = torch.tensor([0.05, -0.02, -0.8])  # M moves points toward the camera
    else:
        true[0, :3, :3] = _rotation(torch.tensor([[0.0, 0.02, 0.0]], dtype=torch.float64))[0]
        true[0, :3, 3] = torch.tensor([0.1, 0.0, -0.5])
    # frame t-1's features: frame t's sampled where frame t-1's cells land under the true motion,
    # so the residual is exactly zero there
    uv = gn.project(gn.apply(true, X), K, 1.0)[0]
    f1 = gn.sample(f2, uv)
    # weight only on the points that frame t sees (the points that leave the image pull the
    # early steps the wrong way)
    seen = valid * ((uv[..., 0] >= 1) & (uv[..., 0] <= w - 2) & (uv[..., 1] >= 1) & (uv[..., 1] <= h - 2))
    gx, gy = gn.image_gradients(f2)
    # from identity to 0.8 m: quadratic convergence sets in after ~9 steps
    M = gn.feature_align(torch.eye(4, dtype=torch.float64)[None], X, torch.cat([f2, gx, gy], 1), f1, seen, K, 14,
                         huber=1e3, damping=1e-4, max_rot=0.05, max_trans=1.0)
    err = gn.invert(true) @ M
    assert float(err[0, :3, 3].norm()) < 1e-4  # m, from a 0.8 m motion
    angle = float(torch.arccos(((err[0, 0, 0] + err[0, 1, 1] + err[0, 2, 2] - 1) / 2).clamp(-1, 1)))
    assert np.degrees(angle) < 1e-3


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
