"""Differentiable, export-friendly Gauss-Newton on SE(3): the geometric pose step dT = P(F, D, T).

Written with elementwise ops, MatMul, GridSample and Where only, so that the flow+pose stage
exports to standard ONNX: the 6x6 normal equations are solved by Gauss-Jordan elimination on
whole matrices (`Inverse` is not in ONNX's default domain; `cramer_solve` where the engine runs
Det), the exponential map by Rodrigues' formula as its Taylor series for a solver step's small
angles. Few ops per step: an exported
graph's time goes to per-op overhead, not arithmetic (docs/performance.md).

Convention: M maps points of frame t-1 into frame t (X_t = R X_{t-1} + t), i.e. the inverse
of the relative pose A (frame t's pose in frame t-1). Updates are left-multiplied:
M <- exp(xi) M with xi = (rho, omega), so that the Jacobian of a transformed point X' is
[I | -[X']x] (PixLoc, DROID-SLAM and DVL-SLAM use the same form).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from . import sampling


# [omega]x.flatten() = SKEW^T omega, written out as a literal: built with in-place writes, the
# tracer would record every write as a graph op
SKEW = [[0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 1, 0, 0, 0, -1, 0, 0], [0, -1, 0, 1, 0, 0, 0, 0, 0]]


# X x a = [I, -I] ((ROLL X) * (ROLL' a)) with ROLL = rows (1, 2, 0) over (2, 0, 1) and ROLL' the
# other way round: a cross product of points along the last axis as three small MatMuls
ROLL = [[0, 1, 0], [0, 0, 1], [1, 0, 0], [0, 0, 1], [1, 0, 0], [0, 1, 0]]
ROLL_BACK = ROLL[3:] + ROLL[:3]
DIFF = [[1, 0, 0, -1, 0, 0], [0, 1, 0, 0, -1, 0], [0, 0, 1, 0, 0, -1]]
# the pixel Jacobians' translation rows from (fx/z, fy/z, -fx x/z^2, -fy y/z^2): d u / d X' in
# rows 0-2, d v / d X' in rows 3-5
PIXEL_ROWS = [[1, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]


def literal(rows, like: torch.Tensor) -> torch.Tensor:
    """A constant of the graph, in like's dtype and device."""
    return torch.tensor(rows, dtype=like.dtype, device=like.device)


def eye_like(n: int, like: torch.Tensor, m: int | None = None) -> torch.Tensor:
    """(n, m) identity as a `literal` (one Constant in an exported graph)."""
    return literal([[float(i == j) for j in range(m or n)] for i in range(n)], like)


def grid_intrinsics(K: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """(B,3,3) G with G X = z (GridSample's x, y, 1) for a camera point X: the intrinsics K (B,4)
    followed by GridSample's pixel -> [-1, 1] map (align_corners), size (w, h) a graph tensor."""
    s = 2.0 / (size - 1.0)  # (2,)
    f, c = K[:, 0:2] * s, K[:, 2:4] * s - 1.0  # (B,2)
    zero = torch.zeros_like(K[:, :1])
    one = torch.ones_like(K[:, :1])
    return torch.stack([torch.cat([f[:, :1], zero, c[:, :1]], 1), torch.cat([zero, f[:, 1:], c[:, 1:]], 1),
                        torch.cat([zero, zero, one], 1)], 1)


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


def unit_diagonal(Hb: torch.Tensor, damped: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[H | b] (B,n,n+1) with H's diagonal replaced by `damped` (B,n,1) -> (d, [D H D | D b]) with
    D = diag(d) = damped^-1/2: the unit-diagonal system whose solution y gives x = d y. Its
    diagonal is written as exactly 1, so that a system without points (H = 0) solves I y = 0
    instead of 0/0."""
    n = Hb.shape[-2]
    d = torch.pow(damped, -0.5)
    pad_one, last_one = eye_like(n, Hb, n + 1), literal([0.0] * n + [1.0], Hb)  # (d^T, 1) = d^T pad_one + last_one
    return d, torch.where(pad_one > 0, literal(1.0, Hb), Hb * (d * (d.transpose(1, 2) @ pad_one + last_one)))


def scaled_solve(Hb: torch.Tensor, damped: torch.Tensor) -> torch.Tensor:
    """x (B,n,1) solving H' x = b for [H | b] (B,n,n+1), H symmetric positive definite, where H' is H
    with its diagonal replaced by `damped` (B,n,1). Scaled to a unit diagonal first
    (`unit_diagonal`): translation and rotation columns differ by orders of magnitude, which
    float32 elimination without pivoting would not survive."""
    d, Hs = unit_diagonal(Hb, damped)
    return d * gauss_jordan(Hs)


def _cramer_columns(n: int) -> list:
    """(n+1, n+1, n) selections: [H | b] @ sel[0] = H, [H | b] @ sel[i] = H with column i-1 := b."""
    sel = []
    for i in range(n + 1):
        rows = [[float(r == c) for c in range(n)] for r in range(n)] + [[0.0] * n]
        if i:
            for r in range(n + 1):
                rows[r][i - 1] = float(r == n)
        sel.append(rows)
    return sel


def cramer_solve(Hb: torch.Tensor, damped: torch.Tensor) -> torch.Tensor:
    """`scaled_solve` by Cramer's rule: the n + 1 determinants of one batched Det op (ONNX Det,
    which onnxruntime runs and OpenVINO does not convert) in place of elimination's 7 ops per
    pivot; on the same unit-diagonal system (`unit_diagonal`), so that H = 0 still solves I x = 0."""
    d, Hs = unit_diagonal(Hb, damped)
    dets = torch.linalg.det(Hs.unsqueeze(1) @ literal(_cramer_columns(Hb.shape[-2]), Hb))  # (B, n+1)
    return d * (dets[:, 1:] / dets[:, :1]).unsqueeze(-1)


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


def sample(x: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear sample (B,C,h,w) at level coordinates (B,N,2) -> (B,C,N); zeros outside."""
    if sampling.gathering():
        return sampling.bilinear(x, uv.transpose(1, 2))
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


def feature_align(M: torch.Tensor, X: torch.Tensor, stack: torch.Tensor, ref: torch.Tensor, weight: torch.Tensor,
                  K: torch.Tensor, iterations: int, huber: float, damping: float, max_rot: float = 0.02,
                  max_trans: float = 0.3) -> torch.Tensor:
    """`iterations` damped Gauss-Newton steps on sum_n weight_n huber(|f2(pi(M X_n)) - f1_n|^2 / C):
    laid out for a short graph (each op costs microseconds whatever its size) as
    `point_solver.align_level` is.
    M (B,4,4); X (B,N,3) frame t-1's points; stack (B,3C,h,w) frame t's C channels and their u, v
    derivatives; ref (B,C,N) frame t-1's channels; weight (B,N); K (B,4) fx, fy, cx, cy in the
    level's cells. Per step: the pose as a (B,3,4) matrix on homogeneous points, the projection
    straight to GridSample's coordinates, the channels folded into five per-point sums (S_uu, S_uv,
    S_vv, S_ru, S_rv), and [H | -g] as one MatMul over the points' u and v Jacobians side by side:
    H = sum_n [Ju, Jv] S_n [Ju, Jv]^T with S_n the 2x2 channel sums."""
    b, c3, h, w = stack.shape
    c, n = c3 // 3, X.shape[1]
    G = grid_intrinsics(K, literal([w, h], K))
    f = K[:, 0:2, None]  # (B,2,1)
    half = literal([[(w - 1) / 2], [(h - 1) / 2]], K)  # grid units -> cells
    P = M[:, :3, :]
    Xh = torch.cat([X, torch.ones_like(X[..., :1])], -1).transpose(1, 2)  # (B,4,N)
    ref = ref.unsqueeze(1)  # (B,1,C,N)
    weight = weight.unsqueeze(1)  # (B,1,N)
    left, right = [0, 0, 1, 1, 2], [1, 2, 1, 2, 2]  # channel sums (r u, r v, u u, u v, v v)
    roll, roll_back, diff = literal(ROLL, X), literal(ROLL_BACK, X), literal(DIFF, X)
    rows = literal(PIXEL_ROWS, X)
    diagonal_at = literal([[8 * i] for i in range(6)], X).long()  # H's diagonal in [H | g] flattened
    to_last = literal([[0.0, 0.0, 0.0, 1.0]], X)  # rho (B,3,1) -> (B,3,4) as the translation column
    limits = literal([max_trans, max_rot], X)
    lattice = sampling.inside_lattice(stack) if sampling.gathering() else None  # once, not at every step
    for _ in range(iterations):
        Xt = P @ Xh  # (B,3,N)
        z = Xt[:, 2:3]
        zi = torch.reciprocal(z.clamp(min=0.1))  # behind the camera: masked by `front`
        grid = (G @ Xt)[:, :2] * zi  # (B,2,N), [-1, 1] inside the image
        # fades from 1 one cell inside the image to 0 at its border: a point crossing the border
        # must not switch its weight on or off (a jump in the solution that float rounding triggers)
        inside = ((1.0 - grid.abs()) * half).amin(1, keepdim=True).clamp(0.0, 1.0)
        if sampling.gathering():  # outside the image `inside` is 0
            smp = sampling.bilinear_inside(stack, grid, lattice).reshape(b, 3, c, n)
        else:
            smp = F.grid_sample(stack, grid.transpose(1, 2).unsqueeze(1), mode="bilinear", padding_mode="zeros",
                                align_corners=True).reshape(b, 3, c, n)  # grey/features, d/du, d/dv
        r = smp[:, :1] - ref  # (B,1,C,N)
        D = torch.cat([r, smp[:, 1:]], 1)
        S = (D[:, left] * D[:, right]).sum(2)  # (B,5,N)
        r2 = (r * r).sum(2).detach() / c  # the Huber weight is a weighting: no gradient
        wgt = weight * (z > 0.1).to(X.dtype) * inside * (huber * torch.rsqrt(r2 + 1e-12)).clamp(max=1.0)
        fz = f * zi
        a = (rows @ torch.cat([fz, -fz * Xt[:, :2] * zi], 1)).reshape(b, 2, 3, n)  # d u / d X', d v / d X'
        a = torch.cat([a[:, 0], a[:, 1]], -1)  # (B,3,2N)
        X2 = torch.cat([Xt, Xt], -1)
        J = torch.cat([a, diff @ ((roll @ X2) * (roll_back @ a))], 1)  # (B,6,2N): [Ju | Jv]
        Jswap = torch.cat([J[..., n:], J[..., :n]], -1)  # [Jv | Ju]
        diag_s = torch.cat([S[:, 2:3], S[:, 4:5]], -1)  # (S_uu | S_vv)
        cross_s = torch.cat([S[:, 3:4], S[:, 3:4]], -1)  # (S_uv | S_uv)
        minus_g = -torch.cat([S[:, 0:1], S[:, 1:2]], -1)  # -(S_ru | S_rv)
        SJ = torch.cat([J * diag_s + Jswap * cross_s, minus_g], 1)  # (B,7,2N)
        Hg = (J * torch.cat([wgt, wgt], -1)) @ SJ.transpose(1, 2)  # (B,6,7): [H | -g]
        # damped by damping diag(H) plus 1e-4 of the mean curvature on every axis: with few points
        # one direction can be nearly unobserved, and float rounding would then decide the step
        dg = Hg.flatten(1)[:, diagonal_at]  # (B,6,1)
        xi = scaled_solve(Hg, dg * (1.0 + damping) + 1e-4 * dg.mean(1, keepdim=True) + 1e-6)  # (B,6,1)
        # a trust region: at most max_trans m and max_rot rad, direction kept, so that a level whose
        # residuals are uninformative (untrained features, a textureless or occluded view) cannot
        # throw the pose far from where the coarser level left it; a good step at 10 Hz is far smaller
        norms = torch.sqrt((xi.reshape(b, 2, 3) ** 2).sum(-1) + 1e-20)  # (B,2)
        xi = xi * (limits / norms).amin(-1, keepdim=True).clamp(max=1.0).unsqueeze(-1)
        P = so3_exp_small(xi[:, 3:]) @ P + xi[:, :3] @ to_last
    return torch.cat([P, M[:, 3:]], 1)


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
