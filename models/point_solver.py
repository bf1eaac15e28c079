"""The pose solver P of eq. 8-9 on the LiDAR point list: direct Gauss-Newton at the image's own resolution.

Frame t-1's textured LiDAR returns (`d3lvo_deploy.points.textured_points`, a fixed-length list with
a mask) are moved by the running motion, projected into frame t's grey image and its pyrDown
levels, and the photometric residual is minimised coarse to fine (with `fine_restart`, the finest
level also alone from the start, the better-explaining pose kept; with `restart_depth`, also where
it fits frame t's own LiDAR scan better; with `scan_gate`, that scan first drops the points that
are no longer where the start puts them). Each level re-estimates a Huber
threshold from the residuals' median (1.345 x 1.4826 x MAD, every `scale_every` steps), takes up to `iterations[l]`
damped steps and stops when a step is below `stop_step` (a flag that zeroes the later steps; the
steps run in blocks of `scale_every`, and at a block boundary after the stop PyTorch breaks and
the exported graph's Loop ends). The network's only say is a
weight per point, its confidence; with every confidence 1 this is exactly the classical tracker
`d3lvo_deploy.direct` (numpy, written separately; a test holds them together).

Standard ONNX ops only: the image pyramids are inputs (`image_pyramids`; cv2 at run time),
GridSample does the bilinear samples, TopK the median, MatMul the normal equations and Gauss-Jordan
elimination the 6x6 solve, Loop the blocks of steps (`export/solver_loop.py`); onnxruntime's graph
samples with one GatherElements (`sampling`) and solves by Cramer's rule (one Det op, which
OpenVINO does not convert). A block of three steps with the exposure match is 588 graph ops (510
in onnxruntime's), each a few microseconds whatever its size, so `gn_steps` is written for few ops and few passes over the
points (`python -m export.solver_bench`, docs/performance.md).
Convention as `gauss_newton`: M maps frame t-1 points into frame t; left updates exp(xi) M.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from . import gauss_newton as gn
from . import sampling
from .gauss_newton import DIFF, ROLL, ROLL_BACK, cramer_solve, grid_intrinsics, literal, scaled_solve, so3_exp_small
from .layers import full_precision
from .sampling import image_size

MAD_TO_SIGMA = 1.4826
# what a masked median sorts last: far above any residual of [0, 1] images or relative depth
# error, and `lidar_depth_error` where no point lands on a return (no evidence)
NO_EVIDENCE = 1e9
HUBER_K = 1.345
_PYR = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0])


@dataclass(frozen=True)
class SolverSettings:
    iterations: tuple[int, ...] = (15, 15, 15)  # coarse to fine; len = pyramid levels
    stop_step: float = 1e-6
    damping: float = 1e-4
    scale_every: int = 3  # the Huber threshold from the residuals' median at every this-th step
    # after the finest level, full weight back to every point the solved pose explains (residual
    # within the Huber threshold) and up to this many more steps there (`restore_explained`)
    refine: int = 0
    # match frame t's grey to frame t-1's at every step (`affine_fit`): an exposure change
    # between the frames otherwise shifts every residual alike, and the solve trades it for motion
    affine: bool = False
    # above 0: also solve the finest level alone from the start, and keep that pose where it
    # explains the points better by more than this (`consensus_gain`): a coarse level can hold a
    # wrong minimum that the finest level then cannot leave, and a constant-velocity start is
    # near the truth at 10 Hz
    fine_restart: float = 0.0
    # above 0 (with frame t's own LiDAR depth, `scan_depth2`): also keep the restart where its
    # `lidar_depth_error` is below this times the coarse-to-fine pose's. Where few points constrain
    # the forward step, the photometric costs can prefer a pose half a metre short; the scan of
    # frame t sees the step (docs/evaluation.md)
    restart_depth: float = 0.0
    # the Huber threshold's median over every this-th point only (`huber_threshold`)
    median_stride: int = 1
    # above 0 (with frame t's own LiDAR depth, `scan_depth2`): before solving, drop the points
    # whose `depth_errors` under the start exceed this (`scan_kept`): what moved, before the
    # solve can follow it (`d3lvo_deploy.direct.scan_gated`)
    scan_gate: float = 0.0


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


def sample_at(img: torch.Tensor, uv: torch.Tensor, inside: bool = False) -> torch.Tensor:
    """Bilinear (G,C,h,w) at pixel positions (B,N,2) -> (B,C,N), zeros outside; h, w as
    `image_size`; B = G, or with `inside` B = k G (rows i k .. i k + k - 1 on image i). inside: the
    caller masks positions outside the image (or has none), so onnxruntime's graph gathers from
    the image as it is (`sampling.bilinear_inside`) instead of padding and transposing all of it
    for a few thousand samples."""
    if sampling.gathering() and not inside:
        return sampling.bilinear(img, uv.transpose(1, 2))
    size = image_size(img, uv.dtype)  # (h, w)
    grid = torch.stack([2.0 * uv[..., 0] / (size[1] - 1) - 1.0, 2.0 * uv[..., 1] / (size[0] - 1) - 1.0], 1)
    if sampling.gathering():
        return sampling.bilinear_inside(img, grid, sampling.inside_lattice(img, uv))
    return sampling.grid_sample_shared(img, grid)


def project(X: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(B,N,3), K (B,4) fx fy cx cy -> pixels (B,N,2), inverse depth (B,N), 'in front' (B,N)."""
    fx, fy, cx, cy = [K[:, i : i + 1] for i in range(4)]
    x, y, z = X.unbind(-1)
    front = (z > 0.1).to(X.dtype)
    zi = 1.0 / z.clamp(min=0.1)
    return torch.stack([fx * x * zi + cx, fy * y * zi + cy], -1), zi, front


def masked_median(a: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """np.median along the last axis of a over mask > 0 (mean of the two middle values for an even
    count): (..., N) -> (..., 1). Masked-out values sort last behind a constant far above any
    residual of [0, 1] images; the middle indices floor((n - 1) / 2), floor(n / 2) never pass N // 2,
    so the smallest N // 2 + 1 values, a partial sort, hold both."""
    v, _ = torch.topk(torch.where(mask > 0, a, literal(NO_EVIDENCE, a)), int(a.shape[-1]) // 2 + 1, dim=-1, largest=False)
    middle = torch.floor((mask.sum(-1, keepdim=True) + literal([-1.0, 0.0], a)) * 0.5).clamp(min=0).long()
    return torch.gather(v, -1, middle).mean(-1, keepdim=True)


def huber_threshold(r: torch.Tensor, mask: torch.Tensor, stride: int = 1) -> torch.Tensor:
    """HUBER_K robust sigmas (1.4826 x the median |r|) of the residuals under mask: (..., 1); with
    `stride`, the median of every stride-th point's (a partial sort of N / stride)."""
    if stride > 1:
        r, mask = r[..., ::stride], mask[..., ::stride]
    return (HUBER_K * MAD_TO_SIGMA * masked_median(r.abs(), mask)).clamp(min=1e-6)


def huber_weights_at(r: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """min(1, k / |r|): 1 where |r| <= k."""
    return (k / r.abs().clamp(min=1e-12)).clamp(max=1.0)


def affine_fit(ref: torch.Tensor, cur: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """a ref + b with the w-weighted mean and spread of cur, along the last axis. Matched moments
    rather than a least-squares fit of cur on ref: far from the solution the two do not correlate,
    a least-squares gain goes to 0 and the residual no longer depends on the pose."""
    sw = w.sum(-1, keepdim=True).clamp(min=1e-30)
    mr, mc = (w * ref).sum(-1, keepdim=True) / sw, (w * cur).sum(-1, keepdim=True) / sw
    vr, vc = (w * (ref - mr) ** 2).sum(-1, keepdim=True) / sw, (w * (cur - mc) ** 2).sum(-1, keepdim=True) / sw
    return torch.sqrt(vc.clamp(min=1e-30) / vr.clamp(min=1e-30)) * (ref - mr) + mc


def gn_steps(P: torch.Tensor, active: torch.Tensor, Xh: torch.Tensor, ref: torch.Tensor, stack: torch.Tensor,
             G: torch.Tensor, f: torch.Tensor, weight: torch.Tensor, w_ok: torch.Tensor, median_mask: torch.Tensor,
             half: torch.Tensor, last_cell: torch.Tensor, row_map: torch.Tensor, offsets: torch.Tensor,
             steps: int, s: SolverSettings, layout: tuple[int, int, int] | None = None
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """`steps` damped Gauss-Newton steps of `align_level` from the pose P (B,3,4) on the points Xh
    (B,4,N), the first one at a multiple of `s.scale_every` (it re-estimates the Huber threshold).
    active (B,1,1) is 1 until a step falls below `s.stop_step`; a stopped level's steps are 0.
    half .. offsets: `sampling.inside_lattice(stack, Xh)`; stack may hold one image per k rows
    (layout: `sampling.grid_sample_shared`'s (k, channels, points), which an export passes as
    constants). Also the body of the exported graph's Loop (`export/solver_loop.py`), so all its
    inputs are tensors of the outer graph.
    onnxruntime's graph (`sampling.gathering`) samples with Gathers and solves the 6x6 system by
    Cramer's rule (one Det op); OpenVINO's by GridSample and Gauss-Jordan elimination (no Det)."""
    diagonal = literal([[8 * i] for i in range(6)], Xh).long()  # H's diagonal in [H | g] flattened
    to_last = literal([[0.0, 0.0, 0.0, 1.0]], Xh)  # rho (B,3,1) -> (B,3,4) as the translation column
    dtype = Xh.dtype
    solve_6x6 = cramer_solve if sampling.gathering() else scaled_solve
    if sampling.gathering():  # the cross product's MatMuls (OpenVINO's graph writes it per row)
        roll, roll_back, diff = literal(ROLL, Xh), literal(ROLL_BACK, Xh), literal(DIFF, Xh)
    for i in range(steps):
        Xt = P @ Xh  # (B,3,N)
        z = Xt[:, 2:3]
        zi = torch.reciprocal(z.clamp(min=0.1))
        grid = (G @ Xt)[:, :2] * zi  # (B,2,N) in [-1, 1] inside the image
        ok = ((grid.abs().amax(1, keepdim=True) <= 1.0) & (z > 0.1)).to(dtype) * w_ok
        active = active * (ok.sum(-1, keepdim=True) >= 12).to(dtype)  # too few: stop, as the tracker
        if sampling.gathering():  # outside the image `ok` is 0
            smp = sampling.bilinear_inside(stack, grid, (half, last_cell, row_map, offsets))  # (B,3,N)
            cur, gxy = smp[:, :1], smp[:, 1:]
        else:
            cur, gx, gy = sampling.grid_sample_channels(stack, grid, layout)  # (B,1,N) each
        # minus the residual: the normal equations come out as [H | -g]; with s.affine, frame t's
        # grey against frame t-1's matched on every point in view, the Huber threshold from that,
        # then matched again with the Huber weights
        nr = (affine_fit(ref, cur, ok * weight) if s.affine else ref) - cur
        if i % s.scale_every == 0:
            k = huber_threshold(nr, ok * median_mask, s.median_stride)
        if s.affine:
            nr = affine_fit(ref, cur, ok * weight * huber_weights_at(nr, k)) - cur
        if sampling.gathering():
            Gz = gxy * (f * zi)  # d grey / d (x/z, y/z)
            a = torch.cat([Gz, -(Gz * Xt[:, :2]).sum(1, keepdim=True) * zi], 1)  # d r / d X', (B,3,N)
            Jr = torch.cat([a, diff @ ((roll @ Xt) * (roll_back @ a)), nr], 1)  # [a, X' x a, -r]
        else:  # the same written out per row: elementwise ops that OpenVINO fuses into one kernel,
            # where the cross product's three small MatMuls are each a kernel of their own
            x, y, zt = Xt.split(1, 1)
            fx, fy = f.split(1, 1)
            au, av = gx * (fx * zi), gy * (fy * zi)
            az = -(au * x + av * y) * zi
            Jr = torch.cat([au, av, az, y * az - zt * av, zt * au - x * az, x * av - y * au, nr], 1)
        w = ok * weight * huber_weights_at(nr, k)
        Hg = ((Jr * w) @ Jr.transpose(1, 2))[:, :6]  # (B,6,7): [H | -g]
        # damped diagonal (1 + damping) diag(H) + 1e-12; a stopped level (no points left, say an
        # empty scan) solves I xi = 0
        xi = solve_6x6(Hg, Hg.flatten(1)[:, diagonal] * (1.0 + s.damping) + 1e-12) * active  # (B,6,1)
        P = so3_exp_small(xi[:, 3:]) @ P + xi[:, :3] @ to_last
        active = active * (xi.abs().amax(1, keepdim=True) >= s.stop_step).to(dtype)
    return P, active


LOOP_DOMAIN, LOOP_OP = "d3lvo", "GaussNewtonLoop"  # the placeholder `export/solver_loop.py` replaces


class _GaussNewtonLoop(torch.autograd.Function):
    """`trips` blocks of `s.scale_every` steps; in an ONNX export one placeholder node that
    `export/solver_loop.py` replaces by a standard Loop over `gn_steps`, which ends when the level
    has stopped (the unrolled graph would compute the same zero steps to the end)."""

    @staticmethod
    def forward(ctx, P, active, Xh, ref, stack, G, f, weight, w_ok, median_mask, half, last_cell, row_map,
                offsets, trips: int, s: SolverSettings, capacity: int, batch: int, images: int):
        if torch.onnx.is_in_onnx_export() and torch.jit.is_tracing():
            # the TorchScript exporter traces this body, then puts `symbolic`'s node in its place:
            # tracing every step (thousands of ops per level) made most of an export's time. The
            # trace keeps only the outputs' shapes and dtypes, which P and active have, so the graph
            # is the same byte for byte; nothing after the solver may branch on tensor values in
            # Python (the trace runs on the unsolved pose)
            return P.clone(), active.clone()
        for _ in range(trips):
            P, active = gn_steps(P, active, Xh, ref, stack, G, f, weight, w_ok, median_mask, half, last_cell,
                                 row_map, offsets, s.scale_every, s)
        return P, active

    @staticmethod
    def symbolic(g, P, active, Xh, ref, stack, G, f, weight, w_ok, median_mask, half, last_cell, row_map,
                 offsets, trips: int, s: SolverSettings, capacity: int, batch: int, images: int):
        out = g.op(f"{LOOP_DOMAIN}::{LOOP_OP}", P, active, Xh, ref, stack, G, f, weight, w_ok, median_mask,
                   half, last_cell, row_map, offsets,
                   trips_i=trips, block_i=s.scale_every, stop_f=s.stop_step, damping_f=s.damping, affine_i=int(s.affine),
                   stride_i=s.median_stride,
                   capacity_i=capacity, batch_i=batch, images_i=images, outputs=2)
        for o, like in zip(out, (P, active)):
            o.setType(like.type())
        return out


def align_level(R: torch.Tensor, t: torch.Tensor, X: torch.Tensor, ref: torch.Tensor, stack: torch.Tensor,
                K: torch.Tensor, weight: torch.Tensor, median_mask: torch.Tensor, iterations: int,
                s: SolverSettings) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to `iterations` Gauss-Newton steps of sum_n weight_n huber(I_t(pi(R X_n + t)) - ref_n).
    R (B,3,3), t (B,1,3) map frame t-1 points into frame t; updates R <- dR R, t <- dR t + rho.
    stack (G,3,h,w): frame t's grey and its derivatives (`with_gradients`), B = k G: rows
    i k .. i k + k - 1 are solves of pair i (`solve`).
    Laid out for a short graph (each op costs microseconds, whatever its size): points along the
    last axis, the pose as one (B,3,4) matrix on homogeneous points, the projection straight to
    GridSample's coordinates, and the normal equations [H | g] as one MatMul of [J | r]. The steps
    run in blocks of `s.scale_every` and stop at the first block boundary after the level has
    stopped: in PyTorch a `break` (not under torch.compile), in an ONNX export a Loop (a stopped
    level's steps are 0, so both give what running every step gives)."""
    dtype = X.dtype
    size = image_size(stack, dtype).flip(0)  # (w, h)
    G = grid_intrinsics(K, size)
    f = K[:, 0:2, None]  # (B,2,1)
    Xh = torch.cat([X, torch.ones_like(X[..., :1])], -1).transpose(1, 2)  # (B,4,N)
    P = torch.cat([R, t.transpose(1, 2)], -1)  # (B,3,4)
    ctx = (Xh, ref.unsqueeze(1), stack, G, f, weight.unsqueeze(1), (weight > 0).to(dtype).unsqueeze(1),
           median_mask.unsqueeze(1), *sampling.inside_lattice(stack, X))
    active = torch.ones_like(K[:, None, :1])  # (B,1,1): 0 once the level has stopped
    trips, rest = divmod(iterations, s.scale_every)
    if torch.onnx.is_in_onnx_export() and trips > 1:
        P, active = _GaussNewtonLoop.apply(P, active, *ctx, trips, s, int(X.shape[1]), int(X.shape[0]),
                                           int(stack.shape[0]))
    else:
        # torch.compile takes every block: a data-dependent break would split its fused graph
        may_break = not (torch.jit.is_tracing() or torch.compiler.is_compiling())
        for _ in range(trips):
            if may_break and not bool(active.amax() > 0):
                break
            P, active = gn_steps(P, active, *ctx, s.scale_every, s)
    if rest:
        P, active = gn_steps(P, active, *ctx, rest, s)
    return P[:, :, :3], P[:, :, 3:].transpose(1, 2)


def residuals_at(R: torch.Tensor, t: torch.Tensor, X: torch.Tensor, ref: torch.Tensor, grey2: torch.Tensor,
                 K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,N) residuals I_t(pi(R X + t)) - ref of frame t-1's points X (B,N,3) under R (B,3,3), t
    (B,1,3), which map them into frame t, in frame t's grey (the first channel of grey2, (G,C,H,W),
    B = k G as `sample_at`: the solver's stack as it is rather than a copy of its grey), and (B,N)
    1 where the point lands in view."""
    uv, _, front = project(X @ R.transpose(1, 2) + t, K)
    h, w = grey2.shape[-2:]
    inside = (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
    return sample_at(grey2, uv, inside=True)[:, 0] - ref, front * inside.to(ref.dtype)


def restore_explained(R: torch.Tensor, t: torch.Tensor, X: torch.Tensor, ref: torch.Tensor, stack: torch.Tensor,
                      K: torch.Tensor, weight: torch.Tensor, mask: torch.Tensor,
                      median_mask: torch.Tensor) -> torch.Tensor:
    """(B,N) weights: `mask` (full weight) where the solved pose R, t explains a point (its residual
    in frame t's grey within the Huber threshold of all residuals), else `weight`. The confidence
    is a prior read before the pose is known; a point that the pose fits is static evidence
    whatever the prior said, and a mover stays down: under the right pose its residual is large."""
    r, seen = residuals_at(R, t, X, ref, stack, K)
    ok = seen * (mask > 0).to(r.dtype)
    k = huber_threshold(r, ok * median_mask)
    return torch.where((r.abs() <= k) & (ok > 0), mask, weight)


def _matrix(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """The relative pose A (frame t in frame t-1, (B,4,4)) of the solver's R, t (frame t-1 points
    into frame t)."""
    bottom = torch.cat([torch.zeros_like(t), torch.ones_like(t[..., :1])], -1)  # (B,1,4)
    return gn.invert(torch.cat([torch.cat([R, t.transpose(1, 2)], -1), bottom], 1))


def _refined(R, t, points, ref, stack, K, weight, median_mask, mask, s: SolverSettings, default_median: bool):
    """`s.refine` more steps after the finest level, with full weight back on the points R, t
    explain (`restore_explained`)."""
    mask = (weight > 0).to(weight.dtype) if mask is None else mask
    weight = restore_explained(R, t, points, ref, stack, K, weight, mask, median_mask)
    median_mask = (weight > 0.5).to(points.dtype) if default_median else median_mask
    return align_level(R, t, points, ref, stack, K, weight, median_mask, s.refine, s)


def _finest_with_restart(R, t, points, ref, stack, K, weight, median_mask, mask, init, k: int, s: SolverSettings,
                         default_median: bool, grey1: torch.Tensor, depth2: torch.Tensor | None) -> torch.Tensor:
    """The finest level from the coarser levels' pose R, t and, in the same batch, alone from the
    start `init` (`DirectConfig.fine_restart`); (B,4,4): the restart's pose where it explains the
    points the solve trusts better by more than `s.fine_restart` (`consensus_gain`), or, with
    `s.restart_depth` and frame t's LiDAR depth `scan_depth2`, where it fits that depth better
    (`lidar_depth_error`), else the coarse-to-fine one. One batch rather than a second solve: a
    step's time is mostly per-op overhead, so twice the rows cost less than two solves (OpenVINO, a
    finest-level block: one row 0.56 ms, two 0.91, four 1.23, `scripts/solver_block_cost.py`). Rows
    per pair: its k coarse-to-fine solves, then their k restarts, on one copy of its images."""
    def two(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.cat([a.reshape(-1, k, *a.shape[1:]), b.reshape(-1, k, *b.shape[1:])], 1).flatten(0, 1)

    M = gn.invert(init)
    X, r, K2, w, med = (two(x, x) for x in (points, ref, K, weight, median_mask))
    R2, t2 = align_level(two(R, M[:, :3, :3]), two(t, M[:, :3, 3].unsqueeze(1)), X, r, stack, K2, w, med,
                         s.iterations[-1], s)
    if s.refine > 0:
        R2, t2 = _refined(R2, t2, X, r, stack, K2, w, med, None if mask is None else two(mask, mask), s, default_median)
    A = _matrix(R2, t2).reshape(-1, 2, k, 4, 4)
    coarse_to_fine, restart = A[:, 0].flatten(0, 1), A[:, 1].flatten(0, 1)
    better = consensus_gain(restart, coarse_to_fine, grey1, stack, points, weight, K) > s.fine_restart
    if s.restart_depth > 0 and depth2 is not None:
        # on the doubled rows the solve ran on: X, K2, w are points, K, weight twice
        errors = lidar_depth_error(A.flatten(0, 2), X, (w >= 0.5).to(X.dtype), depth2, K2).reshape(-1, 2, k)
        better = better | (errors[:, 1] < s.restart_depth * errors[:, 0]).flatten()
    return torch.where(better[:, None, None], restart, coarse_to_fine)


def depth_errors(A: torch.Tensor, points: torch.Tensor, depth2: torch.Tensor,
                 K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,N) |d - z| / z of frame t-1's points (B,N,3) moved by A (B,4,4, frame t in frame t-1)
    against frame t's own LiDAR depth d (G,1,H,W metres, 0 where no return; B = k G, rows i k ..
    i k + k - 1 on image i) at their nearest pixel, and (B,N) 1 where there is evidence: the pixel
    is in view with a return, z above 0.5 m (`d3lvo_deploy.direct.depth_errors`, NaN where none)."""
    M = gn.invert(A)
    X = points @ M[:, :3, :3].transpose(1, 2) + M[:, :3, 3].unsqueeze(1)
    uv = project(X, K)[0]
    size = image_size(depth2, points.dtype)  # (h, w)
    u, v = torch.round(uv[..., 0]), torch.round(uv[..., 1])
    inside = (u >= 0) & (u <= size[1] - 1) & (v >= 0) & (v <= size[0] - 1)
    index = (v.clamp(min=0) * size[1] + u.clamp(min=0)).clamp(max=size[0] * size[1] - 1).long()
    g = depth2.shape[0]
    d = torch.gather(depth2.flatten(1), 1, index.reshape(g, -1)).reshape(index.shape)
    z = X[..., 2]
    return (d - z).abs() / z.clamp(min=0.5), (inside & (d > 0) & (z > 0.5)).to(points.dtype)


@full_precision
def lidar_depth_error(A: torch.Tensor, points: torch.Tensor, trusted: torch.Tensor, depth2: torch.Tensor,
                      K: torch.Tensor) -> torch.Tensor:
    """(B,): the median `depth_errors` of frame t-1's trusted points (B,N) under A; 1e9 where no
    point has evidence. A check of the motion that does not read the images, and that sees the
    forward step; the numpy tracker's `d3lvo_deploy.direct.lidar_depth_error` with every point
    trusted."""
    errors, seen = depth_errors(A, points, depth2, K)
    return masked_median(errors, trusted * seen)[:, 0]


def scan_kept(init: torch.Tensor, points: torch.Tensor, depth2: torch.Tensor, K: torch.Tensor,
              limit: float) -> torch.Tensor:
    """(B,N) 0 where frame t's scan puts a point more than `limit` (`depth_errors`) from where the
    start `init` moves it, else 1 (no evidence keeps it): `SolverSettings.scan_gate`."""
    errors, seen = depth_errors(init, points, depth2, K)
    return 1.0 - seen * (errors > limit).to(points.dtype)


@full_precision
def consensus_gain(A: torch.Tensor, A_classical: torch.Tensor, grey1: torch.Tensor, grey2: torch.Tensor,
                   points: torch.Tensor, weight: torch.Tensor, K: torch.Tensor, cap: float = 2.0) -> torch.Tensor:
    """(B,): how much better the weighted solve's pose A explains the points it trusts (weight at
    least 0.5) than the classical solve's pose A_classical (both (B,4,4), frame t in frame t-1):
    the mean over those points of min(r^2, c^2) under A_classical minus the same under A, c = `cap`
    robust sigmas (1.4826 x the smaller median |r| of the two poses), in units of c^2: RANSAC's
    MSAC cost, on full-resolution grey images of both frames (frame t's as the first channel of
    its (B,C,H,W) stack); weight (B,N) as `solve`'s.
    Something that moves pulls the classical pose off the static points, and they say so; a
    confidence that doubts static points (a false detection) leaves them explained by both."""
    gains, trusted = msac_gains(A, A_classical, grey1, grey2, points, weight, K, cap)
    return (gains * trusted).sum(-1) / trusted.sum(-1).clamp(min=1.0)


@full_precision
def msac_gains(A: torch.Tensor, A_classical: torch.Tensor, grey1: torch.Tensor, grey2: torch.Tensor,
               points: torch.Tensor, weight: torch.Tensor, K: torch.Tensor,
               cap: float = 2.0) -> tuple[torch.Tensor, torch.Tensor]:
    """`consensus_gain` point by point: each point's MSAC cost under A_classical minus under A (B,N),
    and the points it averages over (B,N, 1 where trusted and seen under both poses)."""
    ref = sample_at(grey1, project(points, K)[0], inside=True)[:, 0]  # frame t-1's own points
    M, M_c = gn.invert(A), gn.invert(A_classical)
    r, seen = residuals_at(M[:, :3, :3], M[:, :3, 3:].transpose(1, 2), points, ref, grey2, K)
    r_c, seen_c = residuals_at(M_c[:, :3, :3], M_c[:, :3, 3:].transpose(1, 2), points, ref, grey2, K)
    ok = seen * seen_c * (weight > 0).to(ref.dtype)
    sigma = MAD_TO_SIGMA * torch.minimum(masked_median(r.abs(), ok), masked_median(r_c.abs(), ok))
    limit = (cap * sigma).clamp(min=1e-6) ** 2  # (B,1)
    trusted = ok * (weight >= 0.5).to(ref.dtype)
    cost = lambda x: torch.minimum(x * x / limit, torch.ones_like(x))  # noqa: E731
    return cost(r_c) - cost(r), trusted


def rotations_differ(A: torch.Tensor, B: torch.Tensor, degrees: float) -> torch.Tensor:
    """(batch,) bool: the rotations of A and B (batch,4,4) differ by more than `degrees` (under 90). The
    angle's sine from the skew part of A_R^T B_R: its cosine, from the trace, cannot resolve
    hundredths of a degree in float32."""
    D = A[:, :3, :3].transpose(1, 2) @ B[:, :3, :3]
    v = torch.stack([D[:, 2, 1] - D[:, 1, 2], D[:, 0, 2] - D[:, 2, 0], D[:, 1, 0] - D[:, 0, 1]], -1) * 0.5
    trace = D[:, 0, 0] + D[:, 1, 1] + D[:, 2, 2]
    return ((v * v).sum(-1) > math.sin(math.radians(degrees)) ** 2) | (trace < 1.0)  # (trace - 1) / 2 < 0: past 90


def pyramid_input_names(levels: int) -> tuple[list[str], list[str]]:
    """The flow+pose graph's names for `image_pyramids`' tensors, finest first (what
    `d3lvo_deploy.points.solver_feeds` feeds)."""
    return [f"image1_p{k}" for k in range(levels)], [f"stack2_p{k}" for k in range(levels)]


def image_pyramids(image1: torch.Tensor, image2: torch.Tensor, levels: int) -> tuple[list, list]:
    """The solver's image inputs from both frames' (B,1,H,W) grey images, finest first: frame t-1's
    grey and frame t's grey + derivatives (B,3,h,w) at `levels` pyrDown levels. At run time
    `d3lvo_deploy.points.solver_pyramid` computes the same with cv2, once per frame (frame t's is
    frame t-1's at the next pair), so that the graph does no full-resolution image work."""
    grey1, grey2 = [image1], [image2]
    for _ in range(levels - 1):
        grey1.append(pyr_down(grey1[-1]))
        grey2.append(pyr_down(grey2[-1]))
    return grey1, [with_gradients(g) for g in grey2]


@full_precision
def solve(grey1: list, stack2: list, points: torch.Tensor, weight: torch.Tensor, K: torch.Tensor,
          init: torch.Tensor, s: SolverSettings, median_mask: torch.Tensor | None = None,
          mask: torch.Tensor | None = None, depth2: torch.Tensor | None = None):
    """grey1, stack2 (`image_pyramids`): frame t-1's grey (G,1,h,w) and frame t's grey and
    derivatives (G,3,h,w) at each pyrDown level, finest first, level 0 at the camera's resolution;
    G pairs, each solved k = B / G times from one copy of its images (batch rows i k .. i k + k - 1
    are pair i's solves, which the points, weights, K and init of those rows may set apart);
    points (B,N,3) frame t-1's points in camera coordinates; weight (B,N): the mask times the
    confidence; K (B,4) of the images; init (B,4,4) the starting relative pose A (frame t in
    frame t-1). The Huber scale is taken over the points with median_mask (default weight > 0.5).
    mask (B,N), the point list's (default weight > 0): what `s.refine` restores explained points to.
    depth2 (G,1,H,W): frame t's LiDAR depth at the camera's resolution, for `s.restart_depth` and
    `s.scan_gate`.
    Returns the relative pose A after each level, coarse to fine (the finest after the refinement):
    list of (B,4,4)."""
    if s.scan_gate > 0 and depth2 is not None:
        kept = scan_kept(init, points, depth2, K, s.scan_gate)
        weight, mask = weight * kept, None if mask is None else mask * kept
        median_mask = None if median_mask is None else median_mask * kept
    default_median = median_mask is None
    median_mask = (weight > 0.5).to(points.dtype) if default_median else median_mask
    M = gn.invert(init)
    R, t = M[:, :3, :3], M[:, :3, 3].unsqueeze(1)
    out = []
    for i, lvl in enumerate(reversed(range(len(s.iterations)))):
        Kl = K * (0.5 ** lvl)  # level pixel x sits on source pixel 2^lvl x (pyrDown)
        # frame t-1's points land inside its full-resolution image (a pyrDown level's last column
        # can be half a pixel short of them: zeros beyond, as the numpy tracker's remap); sampled
        # once per pair where k solves share it
        k = points.shape[0] // grey1[lvl].shape[0]
        first = (points[::k], Kl[::k]) if k > 1 else (points, Kl)
        ref = sample_at(grey1[lvl], project(*first)[0], inside=lvl == 0)[:, 0]
        ref = ref.unsqueeze(1).expand(-1, k, -1).flatten(0, 1) if k > 1 else ref
        if lvl == 0 and s.fine_restart > 0 and len(s.iterations) > 1:
            out.append(_finest_with_restart(R, t, points, ref, stack2[0], Kl, weight, median_mask, mask, init, k,
                                            s, default_median, grey1[0], depth2))
            continue
        R, t = align_level(R, t, points, ref, stack2[lvl], Kl, weight, median_mask, s.iterations[i], s)
        if lvl == 0 and s.refine > 0:
            R, t = _refined(R, t, points, ref, stack2[0], Kl, weight, median_mask, mask, s, default_median)
        out.append(_matrix(R, t))
    return out
