"""The pose solver P of eq. 8-9 on the LiDAR point list: direct Gauss-Newton at the image's own resolution.

Frame t-1's textured LiDAR returns (`d3lvo_deploy.points.textured_points`, a fixed-length list with
a mask) are moved by the running motion, projected into frame t's grey image and its pyrDown
levels, and the photometric residual is minimised coarse to fine. Each level re-estimates a Huber
threshold from the residuals' median (1.345 x 1.4826 x MAD), takes up to `iterations[l]`
damped steps and stops when a step is below `stop_step` (a flag that zeroes the later steps, so
the unrolled graph computes what a loop with `break` computes). The network's only say is a
weight per point, its confidence; with every confidence 1 this is exactly the classical tracker
`d3lvo_deploy.direct` (numpy, written separately; a test holds them together).

Standard ONNX ops only: Pad + Conv for pyrDown, GridSample for the bilinear samples, TopK for the
median, MatMul for the normal equations and Gauss-Jordan elimination for the 6x6 solve.
Convention as `gauss_newton`: M maps frame t-1 points into frame t; left updates exp(xi) M.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from . import gauss_newton as gn
from .layers import full_precision

MAD_TO_SIGMA = 1.4826
HUBER_K = 1.345
_PYR = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0])


@dataclass(frozen=True)
class SolverSettings:
    iterations: tuple[int, ...] = (15, 15, 15)  # coarse to fine; len = pyramid levels
    stop_step: float = 1e-6
    damping: float = 1e-4


def pyr_down(x: torch.Tensor) -> torch.Tensor:
    """cv2.pyrDown: 5x5 binomial blur with reflect-101 borders, every second pixel (B,1,H,W)."""
    k = (_PYR[:, None] * _PYR[None, :] / 256.0).to(x)
    return F.conv2d(F.pad(x, (2, 2, 2, 2), mode="reflect"), k.view(1, 1, 5, 5), stride=2)


def with_gradients(g: torch.Tensor) -> torch.Tensor:
    """(B,1,H,W) -> (B,3,H,W): grey, d/du, d/dv by central differences with replicated edges."""
    p = F.pad(g, (1, 1, 1, 1), mode="replicate")
    gx = (p[..., 1:-1, 2:] - p[..., 1:-1, :-2]) * 0.5
    gy = (p[..., 2:, 1:-1] - p[..., :-2, 1:-1]) * 0.5
    return torch.cat([g, gx, gy], 1)


def sample_at(img: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear (B,C,h,w) at pixel positions (B,N,2) -> (B,C,N), zeros outside; h, w read from the
    tensor's shape as a tensor, so that the exported graph takes any image size."""
    size = torch._shape_as_tensor(img)[2:].to(uv.dtype)  # (h, w)
    gx = 2.0 * uv[..., 0] / (size[1] - 1) - 1.0
    gy = 2.0 * uv[..., 1] / (size[0] - 1) - 1.0
    grid = torch.stack([gx, gy], -1).unsqueeze(1)
    return F.grid_sample(img, grid, mode="bilinear", padding_mode="zeros", align_corners=True)[:, :, 0]


def project(X: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(B,N,3), K (B,4) fx fy cx cy -> pixels (B,N,2), inverse depth (B,N), 'in front' (B,N)."""
    fx, fy, cx, cy = [K[:, i : i + 1] for i in range(4)]
    x, y, z = X.unbind(-1)
    front = (z > 0.1).to(X.dtype)
    zi = 1.0 / z.clamp(min=0.1)
    return torch.stack([fx * x * zi + cx, fy * y * zi + cy], -1), zi, front


def masked_median(a: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """np.median of a (B,N) over mask > 0 (mean of the two middle values for an even count)."""
    big = a.detach().abs().amax(-1, keepdim=True) + 1.0
    v, _ = torch.sort(torch.where(mask > 0, a, big), dim=-1)
    n = mask.sum(-1, keepdim=True).clamp(min=1.0)
    lo = torch.floor((n - 1) * 0.5).long()
    hi = torch.floor(n * 0.5).long().clamp(max=a.shape[-1] - 1)
    return 0.5 * (torch.gather(v, -1, lo) + torch.gather(v, -1, hi))


def huber_scale_weights(r: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Huber weights with the threshold at HUBER_K robust sigmas of the residuals under mask."""
    a = r.abs()
    k = (HUBER_K * MAD_TO_SIGMA * masked_median(a, mask)).clamp(min=1e-6)
    return torch.where(a <= k, torch.ones_like(a), k / a.clamp(min=1e-12))


# X x a = (X outer a).flatten() @ LEVI_CIVITA (9, 3); [omega]x.flatten() = omega @ SKEW (3, 9). Written
# out as literals: built with in-place writes, the tracer would record every write as a graph op
LEVI_CIVITA = [[0, 0, 0], [0, 0, 1], [0, -1, 0], [0, 0, -1], [0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, 0, 0]]
SKEW = [[0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 1, 0, 0, 0, -1, 0, 0], [0, -1, 0, 1, 0, 0, 0, 0, 0]]


def _const(rows, like: torch.Tensor) -> torch.Tensor:
    return torch.tensor(rows, dtype=like.dtype, device=like.device)


def _eye(n: int, like: torch.Tensor) -> torch.Tensor:
    return _const([[float(i == j) for j in range(n)] for i in range(n)], like)


def gauss_jordan_solve(A: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Solve A x = b for symmetric positive definite (B,n,n) A and (B,n,1) b: Gauss-Jordan on
    [A | b] without pivoting (stable for SPD, as LDL^T), a handful of whole-matrix ops per pivot
    instead of an unrolled Cholesky's scalar ones (each op of a graph costs microseconds)."""
    n = A.shape[-1]
    Ab = torch.cat([A, b], -1)
    eye = _eye(n, A)
    for k in range(n):
        row = Ab[:, k : k + 1, :] / Ab[:, k : k + 1, k : k + 1]
        Ab = Ab - (Ab[:, :, k : k + 1] - eye[:, k : k + 1]) * row
    return Ab[:, :, n:]


def so3_exp_small(omega: torch.Tensor) -> torch.Tensor:
    """(B,3) -> (B,3,3): Rodrigues with sin(t)/t and (1-cos t)/t^2 as their series to t^4, exact
    to float64 rounding below 0.05 rad and to 1e-7 at 0.3 rad; a solver step is far smaller."""
    th2 = (omega * omega).sum(-1, keepdim=True).unsqueeze(-1)
    K = (omega @ _const(SKEW, omega)).reshape(-1, 3, 3)
    a = 1.0 - th2 / 6.0 + th2 * th2 / 120.0
    b = 0.5 - th2 / 24.0 + th2 * th2 / 720.0
    return _eye(3, omega) + a * K + b * (K @ K)


def align_level(R: torch.Tensor, t: torch.Tensor, X: torch.Tensor, ref: torch.Tensor, stack: torch.Tensor,
                K: torch.Tensor, weight: torch.Tensor, median_mask: torch.Tensor, iterations: int,
                s: SolverSettings) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to `iterations` Gauss-Newton steps of sum_n weight_n huber(I_t(pi(R X_n + t)) - ref_n).
    R (B,3,3), t (B,1,3) map frame t-1 points into frame t; updates R <- dR R, t <- t dR^T + rho."""
    dtype = X.dtype
    size = torch._shape_as_tensor(stack)[2:].to(dtype).flip(0)  # (w, h)
    wh1 = size - 1.0
    to_grid = 2.0 / wh1  # pixel -> GridSample's [-1, 1] (align_corners)
    f = K[:, None, 0:2]  # (B,1,2) fx, fy
    c = K[:, None, 2:4]
    E = _const(LEVI_CIVITA, X)
    eye6 = _eye(6, X)
    active = torch.ones_like(K[:, None, :1])  # (B,1,1): 0 once the level has stopped
    w_ok = (weight > 0).to(dtype)
    for _ in range(iterations):
        Xt = X @ R.transpose(1, 2) + t
        xy, z = Xt[..., :2], Xt[..., 2:]
        zi = 1.0 / z.clamp(min=0.1)
        uv = f * xy * zi + c
        inside = (uv.amin(-1) >= 0).to(dtype) * ((uv - wh1).amax(-1) <= 0).to(dtype)
        ok = inside * (z[..., 0] > 0.1).to(dtype) * w_ok
        active = active * (ok.sum(-1, keepdim=True) >= 12).to(dtype).unsqueeze(-1)  # too few: stop, as the tracker
        smp = F.grid_sample(stack, (uv * to_grid - 1.0).unsqueeze(1), mode="bilinear", padding_mode="zeros",
                            align_corners=True)[:, :, 0].transpose(1, 2)  # (B,N,3)
        r = smp[..., 0] - ref
        G = smp[..., 1:] * f  # (B,N,2) image gradient times focal length
        a = torch.cat([G * zi, -(G * xy).sum(-1, keepdim=True) * zi * zi], -1)  # d r / d X'
        J = torch.cat([a, (Xt.unsqueeze(-1) * a.unsqueeze(-2)).flatten(2) @ E], -1)  # [a, X' x a]
        Jw = J * (ok * weight * huber_scale_weights(r, ok * median_mask)).unsqueeze(-1)
        JwT = Jw.transpose(1, 2)
        H = JwT @ J
        g = JwT @ r.unsqueeze(-1)  # (B,6,1)
        diag = (H * eye6).sum(-1, keepdim=True)  # (B,6,1)
        # scaled to a unit diagonal first: translation and rotation columns differ by orders of
        # magnitude, which float32 elimination without pivoting would not survive
        d = 1.0 / torch.sqrt(diag * (1.0 + s.damping) + 1e-12)
        # a stopped level (no points left, say an empty scan) solves I xi = 0 instead of 0/0
        Hs = H * d * d.transpose(1, 2) + eye6 * (s.damping * diag * d * d + (1.0 - active))
        xi = -(d * gauss_jordan_solve(Hs, d * g))[..., 0] * active[:, 0]
        dR = so3_exp_small(xi[:, 3:])
        R = dR @ R
        t = t @ dR.transpose(1, 2) + xi[:, None, :3]
        active = active * (xi.abs().amax(-1, keepdim=True) >= s.stop_step).to(dtype).unsqueeze(-1)
    return R, t


@full_precision
def solve(image1: torch.Tensor, image2: torch.Tensor, points: torch.Tensor, weight: torch.Tensor,
          K: torch.Tensor, init: torch.Tensor, s: SolverSettings, median_mask: torch.Tensor | None = None):
    """image1, image2: (B,1,H,W) grey [0,1] of frames t-1 and t at the camera's resolution;
    points (B,N,3) frame t-1's points in camera coordinates; weight (B,N): the mask times the
    confidence; K (B,4) of the images; init (B,4,4) the starting relative pose A (frame t in
    frame t-1). The Huber scale is taken over the points with median_mask (default weight > 0.5).
    Returns the relative pose A after each level, coarse to fine: list of (B,4,4)."""
    pyr1, pyr2 = [image1], [image2]
    for _ in range(len(s.iterations) - 1):
        pyr1.append(pyr_down(pyr1[-1]))
        pyr2.append(pyr_down(pyr2[-1]))
    median_mask = (weight > 0.5).to(points.dtype) if median_mask is None else median_mask
    M = gn.invert(init)
    R, t = M[:, :3, :3], M[:, :3, 3].unsqueeze(1)
    bottom = init[:, 3:, :]
    out = []
    for i, lvl in enumerate(reversed(range(len(s.iterations)))):
        Kl = K * (0.5 ** lvl)  # level pixel x sits on source pixel 2^lvl x (pyrDown)
        ref = sample_at(pyr1[lvl], project(points, Kl)[0])[:, 0]
        R, t = align_level(R, t, points, ref, with_gradients(pyr2[lvl]), Kl, weight, median_mask, s.iterations[i], s)
        out.append(gn.invert(torch.cat([torch.cat([R, t.transpose(1, 2)], -1), bottom], 1)))
    return out
