"""Differentiable, export-friendly Gauss-Newton on SE(3): the geometric pose step dT = P(F, D, T).

Written with elementwise ops, MatMul, GridSample and Where only, so that the flow+pose stage
exports to standard ONNX: the 6x6 normal equations are solved by Gauss-Jordan elimination on
whole matrices (`Inverse` is not in ONNX's default domain), the exponential map by Rodrigues'
formula as its Taylor series for a solver step's small angles. Few ops per step: an exported
graph's time goes to per-op overhead, not arithmetic (docs/performance.md).

Convention: M maps points of frame t-1 into frame t (X_t = R X_{t-1} + t), i.e. the inverse
of the relative pose A (frame t's pose in frame t-1). Updates are left-multiplied:
M <- exp(xi) M with xi = (rho, omega), so that the Jacobian of a transformed point X' is
[I | -[X']x] (PixLoc, DROID-SLAM and DVL-SLAM use the same form).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


# [omega]x.flatten() = SKEW^T omega, written out as a literal: built with in-place writes, the
# tracer would record every write as a graph op
SKEW = [[0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 1, 0, 0, 0, -1, 0, 0], [0, -1, 0, 1, 0, 0, 0, 0, 0]]


def literal(rows, like: torch.Tensor) -> torch.Tensor:
    """A constant of the graph, in like's dtype and device."""
    return torch.tensor(rows, dtype=like.dtype, device=like.device)


def eye_like(n: int, like: torch.Tensor, m: int | None = None) -> torch.Tensor:
    """(n, m) identity as a `literal` (one Constant in an exported graph)."""
    return literal([[float(i == j) for j in range(m or n)] for i in range(n)], like)


def gauss_jordan(Ab: torch.Tensor) -> torch.Tensor:
    """[A | b] (B,n,n+1) -> x (B,n,1) for symmetric positive definite A: Gauss-Jordan without
    pivoting (stable for SPD, as LDL^T), seven whole-matrix ops per pivot instead of an unrolled
    Cholesky's scalar ones (each op of a graph costs microseconds)."""
    n = Ab.shape[-2]
    eye = eye_like(n, Ab)
    for k in range(n):
        row = Ab[:, k : k + 1, :]
        Ab = Ab - (Ab[:, :, k : k + 1] - eye[:, k : k + 1]) * (row / row[:, :, k : k + 1])
    return Ab[:, :, n:]


def gauss_jordan_solve(A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Solve A x = b for SPD (B,n,n) A and (B,n,1) b."""
    return gauss_jordan(torch.cat([A, b], -1))


def diagonal(A: torch.Tensor) -> torch.Tensor:
    """(B,n,n) -> (B,n) as one Gather on the flattened matrix (torch.diagonal exports as
    EyeLike + If, and indexing element by element as n Gathers)."""
    n = A.shape[-1]
    return A.flatten(1)[:, [(n + 1) * i for i in range(n)]]


def spd_solve(H: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Solve H x = g for SPD (B,n,n) H and (B,n) g in float32: scaled to a unit diagonal first
    (translation and rotation columns differ by orders of magnitude, which elimination without
    pivoting would not survive), then `gauss_jordan`."""
    d = torch.rsqrt(diagonal(H).clamp(min=1e-30)).unsqueeze(-1)  # (B,n,1)
    return (d * gauss_jordan(torch.cat([H * (d @ d.transpose(1, 2)), d * g.unsqueeze(-1)], -1)))[..., 0]


def so3_exp_small(omega: torch.Tensor) -> torch.Tensor:
    """(B,3) or (B,3,1) -> (B,3,3): Rodrigues with sin(t)/t and (1-cos t)/t^2 as their series to
    t^4, exact to float64 rounding below 0.05 rad and to 1e-7 at 0.3 rad; a solver step is far
    smaller (and a few ops, where a sin/cos branch takes thirty)."""
    if omega.dim() == 2:
        omega = omega.unsqueeze(-1)
    th2 = (omega * omega).sum(1, keepdim=True)  # (B,1,1)
    K = (literal(SKEW, omega).transpose(0, 1) @ omega).reshape(-1, 3, 3)
    ab = literal([1.0, 0.5], omega) + th2 * (literal([-1.0 / 6.0, -1.0 / 24.0], omega)
                                             + th2 * literal([1.0 / 120.0, 1.0 / 720.0], omega))  # (B,1,2)
    return eye_like(3, omega) + ab[..., :1] * K + ab[..., 1:] * (K @ K)


def backproject(invdepth: torch.Tensor, K: torch.Tensor, scale: float, min_depth: float):
    """Pixel grid of a pyramid level -> (B,N,3) points of frame t-1 and (B,N) validity.

    invdepth: (B,1,h,w) as min_depth / d (0 = unknown); K: (B,4) fx, fy, cx, cy at the network
    input; level cell (i, j) is input pixel (scale*j, scale*i) (a stride-2 conv with padding 1
    centres output i on input 2i)."""
    b, _, h, w = invdepth.shape
    fx, fy, cx, cy = [K[:, i].view(b, 1, 1) for i in range(4)]
    v = torch.arange(h, dtype=K.dtype, device=K.device).view(1, h, 1) * scale
    u = torch.arange(w, dtype=K.dtype, device=K.device).view(1, 1, w) * scale
    inv = invdepth[:, 0]
    valid = inv > 1e-4
    z = min_depth / inv.clamp(min=1e-4)  # no depth: masked by `valid`
    X = torch.stack([(u - cx) / fx * z, (v - cy) / fy * z, z.expand(b, h, w)], -1)
    return X.reshape(b, h * w, 3), valid.reshape(b, h * w).to(K.dtype)


def project(X: torch.Tensor, K: torch.Tensor, scale: float):
    """(B,N,3) -> level-grid coordinates (B,N,2) and (B,N) 'in front of the camera'."""
    fx, fy, cx, cy = [K[:, i].view(-1, 1) / scale for i in range(4)]
    x, y, z = X.unbind(-1)
    front = (z > 0.1).to(X.dtype)
    zi = 1.0 / z.clamp(min=0.1)  # behind the camera: masked by `front`
    return torch.stack([fx * x * zi + cx, fy * y * zi + cy], -1), front


def pixel_jacobian(X: torch.Tensor, K: torch.Tensor, scale: float) -> torch.Tensor:
    """d pi(exp(xi) X) / d xi at xi = 0, in level cells: (B,N,2,6). The projection's 2x3
    Jacobian times [I | -[X]x], multiplied out (row a of it is [a, X x a]); its zeros are made
    from the data (x * 0), since a zeros_like of a static shape is folded into the graph as a
    constant per call (10 MB of them at 608x176)."""
    fx, fy = [K[:, i].view(-1, 1) / scale for i in range(2)]
    x, y, z = X.unbind(-1)
    zi = 1.0 / z.clamp(min=0.1)  # behind the camera: masked by `front`
    xz, yz, o = x * zi, y * zi, x * 0.0
    ju = [fx * zi, o, -fx * xz * zi, -fx * xz * yz, fx * (1 + xz * xz), -fx * yz]
    jv = [o, fy * zi, -fy * yz * zi, -fy * (1 + yz * yz), fy * xz * yz, fy * xz]
    return torch.stack(ju + jv, -1).reshape(X.shape[:-1] + (2, 6))


def sample(x: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear sample (B,C,h,w) at level coordinates (B,N,2) -> (B,C,N); zeros outside."""
    h, w = x.shape[-2:]
    gx = 2.0 * uv[..., 0] / max(w - 1, 1) - 1.0
    gy = 2.0 * uv[..., 1] / max(h - 1, 1) - 1.0
    grid = torch.stack([gx, gy], -1).unsqueeze(1)  # (B,1,N,2)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=True)[:, :, 0]


def image_gradients(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Central differences (one-sided at the border), per channel."""
    gx = torch.cat([x[..., :, 1:2] - x[..., :, :1], (x[..., :, 2:] - x[..., :, :-2]) / 2, x[..., :, -1:] - x[..., :, -2:-1]], -1)
    gy = torch.cat([x[..., 1:2, :] - x[..., :1, :], (x[..., 2:, :] - x[..., :-2, :]) / 2, x[..., -1:, :] - x[..., -2:-1, :]], -2)
    return gx, gy


def apply(M: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """(B,4,4) x (B,N,3) -> (B,N,3)."""
    return X @ M[:, :3, :3].transpose(1, 2) + M[:, :3, 3].unsqueeze(1)


def update(M: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """exp(xi) M with the decoupled left update (R <- dR R, t <- dR t + rho), the exact
    counterpart of the Jacobian [I | -[X']x]."""
    dR = so3_exp_small(xi[:, 3:])  # a step is at most `damped_step`'s max_rot
    R = dR @ M[:, :3, :3]
    t = (dR @ M[:, :3, 3:]) + xi[:, :3].unsqueeze(-1)
    bottom = M[:, 3:, :]
    return torch.cat([torch.cat([R, t], -1), bottom], 1)


def normal_equations(J: torch.Tensor, r: torch.Tensor, w: torch.Tensor):
    """J (B,N,k,6), r (B,N,k), w (B,N) -> H (B,6,6), g (B,6) of sum_n w_n |r_n + J_n xi|^2."""
    Jw = J * w.unsqueeze(-1).unsqueeze(-1)
    b = J.shape[0]
    H = Jw.reshape(b, -1, 6).transpose(1, 2) @ J.reshape(b, -1, 6)
    g = (Jw.reshape(b, -1, 6) * r.reshape(b, -1, 1)).sum(1)
    return H, g


def feature_normal_equations(Jp: torch.Tensor, r: torch.Tensor, gu: torch.Tensor, gv: torch.Tensor,
                             w: torch.Tensor):
    """H, g of sum_n w_n sum_c (r_cn + (gu_cn Ju_n + gv_cn Jv_n) xi)^2 without forming the
    (N, C, 6) Jacobian: sum_c J^T J = Ju^T Ju S_uu + (Ju^T Jv + Jv^T Ju) S_uv + Jv^T Jv S_vv with
    per-point channel sums S, and g = Ju S_ru + Jv S_rv. The same numbers as `normal_equations` on
    the full Jacobian, C times less work and no batched 2x6 products (slow as graph ops).
    Jp (B,N,2,6) pixel Jacobian; r, gu, gv (B,C,N) residual and feature gradients; w (B,N)."""
    Ju, Jv = Jp[:, :, 0], Jp[:, :, 1]  # (B,N,6)
    suu, suv, svv = ((gu * gu).sum(1) * w, (gu * gv).sum(1) * w, (gv * gv).sum(1) * w)
    sru, srv = (r * gu).sum(1) * w, (r * gv).sum(1) * w
    JuT, JvT = Ju.transpose(1, 2), Jv.transpose(1, 2)
    cross = JuT @ (Jv * suv.unsqueeze(-1))
    H = JuT @ (Ju * suu.unsqueeze(-1)) + cross + cross.transpose(1, 2) + JvT @ (Jv * svv.unsqueeze(-1))
    g = (Ju * sru.unsqueeze(-1)).sum(1) + (Jv * srv.unsqueeze(-1)).sum(1)
    return H, g


def damped_step(H: torch.Tensor, g: torch.Tensor, damping: float, max_rot: float = 0.02,
                max_trans: float = 0.3) -> torch.Tensor:
    """Levenberg-Marquardt step -inv(H + lambda diag(H) + floor I) g, scaled down (direction kept)
    to at most `max_rot` rad and `max_trans` m: a trust region, so that a level whose residuals
    are uninformative (untrained depth, a textureless or occluded view) cannot throw the pose far
    from where the coarser level left it; a good step at 10 Hz is far smaller."""
    eye = torch.eye(6, dtype=H.dtype, device=H.device)
    diag = diagonal(H)
    # plus 1e-4 of the mean curvature on every axis: with few points (a coarse level, a sparse
    # scan) one direction can be nearly unobserved, and float rounding would then decide the step
    floor = 1e-4 * diag.mean(-1, keepdim=True) + 1e-6
    Hd = H + eye * (damping * diag + floor).unsqueeze(-1)
    xi = -spd_solve(Hd, g)
    rho_n = torch.sqrt((xi[:, :3] ** 2).sum(-1, keepdim=True) + 1e-20)
    om_n = torch.sqrt((xi[:, 3:] ** 2).sum(-1, keepdim=True) + 1e-20)
    shrink = torch.minimum(torch.minimum(max_trans / rho_n, max_rot / om_n), torch.ones_like(rho_n))
    return xi * shrink


def huber_weights(r2: torch.Tensor, delta: float) -> torch.Tensor:
    """IRLS weights of the Huber loss on residual norms sqrt(r2); no gradient (a weighting)."""
    n = torch.sqrt(r2.detach() + 1e-12)
    return torch.where(n <= delta, torch.ones_like(n), delta / n)


def matrix_to_pose(M: torch.Tensor) -> torch.Tensor:
    """(B,4,4) -> (B,7) translation + quaternion (w, x, y, z), w >= 0; branch-free (Where)
    so that it exports; well conditioned near identity, which frame-to-frame motion is."""
    R = M[:, :3, :3]
    t = M[:, :3, 3]
    tr = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    w = 0.5 * torch.sqrt((1 + tr).clamp(min=1e-8))
    x = (R[:, 2, 1] - R[:, 1, 2]) / (4 * w)
    y = (R[:, 0, 2] - R[:, 2, 0]) / (4 * w)
    z = (R[:, 1, 0] - R[:, 0, 1]) / (4 * w)
    return torch.cat([t, torch.stack([w, x, y, z], -1)], -1)


def invert(M: torch.Tensor) -> torch.Tensor:
    Rt = M[:, :3, :3].transpose(1, 2)
    t = -(Rt @ M[:, :3, 3:])
    return torch.cat([torch.cat([Rt, t], -1), M[:, 3:, :]], 1)
