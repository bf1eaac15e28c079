"""The LiDAR points a direct solver tracks: frame t-1's returns that the camera sees, on texture.

One selection serves the classical tracker (`d3lvo run --method direct`) and the network's point
solver (the flow+pose graph's `points1` input), so that the network with its confidence set to 1
solves exactly the classical problem. The points stay 3D points in image_2 camera coordinates:
no pooling to cells, no resizing of the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .projection import rows_in_depth, sparse_depth

# the flow+pose graph's input for frame t's LiDAR depth, where it checks the finest level's restart
# against the scan (`pt_restart_depth`), gates the points by it (`pt_scan_gate`) or judges the two
# poses by it (`pt_select_scan_pass`)
SCAN_DEPTH_INPUT = "scan_depth2"
# the classical mode's pose of the pair (frame t in frame t-1, (1,4,4)): the `classical` stage's
# output and, where a model folder has that stage, an input of its `flowpose_weighted` graph
CLASSICAL_INPUT = "classical_pose"
# with `pt_classical_chain`: where the flow+pose graph that solves both poses starts the classical
# solve ((1,4,4), the previous pair's classical pose), and the classical pose it outputs for the next
CLASSICAL_START_INPUT = "classical_start"
CLASSICAL_NEXT_OUTPUT = "classical_next"


@dataclass
class PointConfig:
    min_gradient: float = 0.02  # |grad| of frame t-1's grey [0, 1] image where a point is kept
    min_depth: float = 0.5
    max_depth: float = 120.0
    occlusion_window: int = 5  # points behind a nearer return in this window (pixels, square) are dropped
    occlusion_margin: float = 0.1  # ... when farther than (1 + margin) x the nearest one
    # the most points a frame gives (the exported graph's fixed point-list length). Real KITTI
    # frames give ~4,500 textured returns, 620x188 synthetic ones 8,000-14,000. Measured
    # (docs/evaluation.md): 2,048 tracks static drives and the real frames as well as every return,
    # and a traffic drive nearly as well as 4,096, at half the solver's work
    capacity: int = 2048


def grey_image(image: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(H,W,3) uint8 RGB (or (H,W) grey) -> (H,W) float32 grey in [0, 1] (written into `out`)."""
    g = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    return np.divide(g, np.float32(255.0), out=out, dtype=np.float32)


def gradients(grey: np.ndarray, out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Central differences, edges replicated (the solver's own; the graph computes the same);
    written into `out` (2, H, W) float32 where given."""
    out = np.empty((2, *grey.shape), np.float32) if out is None else out
    for k, (dx, dy) in enumerate(((1, 0), (0, 1))):
        cv2.Sobel(grey, cv2.CV_32F, dx, dy, dst=out[k], ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
    return out[0], out[1]


def project(X: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) camera points -> (N, 2) pixels and their inverse depth."""
    zi = 1.0 / X[:, 2]
    uv = np.stack([K[0, 0] * X[:, 0] * zi + K[0, 2], K[1, 1] * X[:, 1] * zi + K[1, 2]], 1)
    return uv, zi


def in_depth_range(points: np.ndarray, T_cam_velo: np.ndarray, min_depth: float, max_depth: float) -> np.ndarray:
    """(N, >=3) LiDAR points -> (M, 3) float64 camera points with min_depth < z < max_depth: the
    same points and values as transforming every return, but only the half of a 360-degree scan
    ahead of the camera is converted to float64 and transformed (`rows_in_depth`)."""
    near = rows_in_depth(points, T_cam_velo[2], min_depth, max_depth)
    h = np.empty((len(near), 4), np.float64)  # homogeneous: one GEMM, no (N, 3) broadcast add
    h[:, :3], h[:, 3] = near[:, :3], 1.0
    X = h @ np.asarray(T_cam_velo, np.float64)[:3].T
    return np.compress((X[:, 2] > min_depth) & (X[:, 2] < max_depth), X, axis=0)


def visible_points(points: np.ndarray, T_cam_velo: np.ndarray, K: np.ndarray, shape: tuple[int, int],
                   cfg: PointConfig) -> np.ndarray:
    """The scan's returns in the camera frame that the camera sees: in the image, in the depth range,
    and not hidden behind a nearer return nearby (the LiDAR sits above the camera, so it sees
    surfaces behind a car's edge that the camera does not)."""
    X = in_depth_range(points, T_cam_velo, cfg.min_depth, cfg.max_depth)
    uv, _ = project(X, K)
    h, w = shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    X, uv = np.compress(inside, X, axis=0), np.compress(inside, uv, axis=0)
    if cfg.occlusion_window > 1 and len(X):
        c, r = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
        zbuf = np.full(h * w, np.inf, np.float32)
        np.minimum.at(zbuf, r * w + c, X[:, 2].astype(np.float32))
        k = np.ones((cfg.occlusion_window, cfg.occlusion_window), np.uint8)
        nearest = cv2.erode(zbuf.reshape(h, w), k, borderType=cv2.BORDER_REPLICATE)
        X = np.compress(X[:, 2] <= (1.0 + cfg.occlusion_margin) * nearest[r, c], X, axis=0)
    return X


def bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear sample of an (h, w[, c]) image at (N, 2) pixel positions -> (N[, c]); 0 outside."""
    n = len(uv)
    rows = max(-(-n // 1024), 1)  # remap maps must stay under 32767 columns: rows of 1024 points
    m = np.full((rows * 1024, 2), -1.0, np.float32)
    m[:n] = uv
    out = cv2.remap(img, m.reshape(rows, 1024, 2), None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=0.0)
    return out.reshape((rows * 1024,) + img.shape[2:])[:n]


def textured_points(scan: np.ndarray, T_cam_velo: np.ndarray, K: np.ndarray, grey: np.ndarray,
                    cfg: PointConfig, grads: tuple[np.ndarray, np.ndarray] | np.ndarray | None = None) -> np.ndarray:
    """(M, 3) camera points, M <= capacity: visible returns where |grad grey| > min_gradient, an
    evenly spaced subset when there are more than `capacity`. Not the strongest gradients: with
    traffic those lie on the vehicles' edges, and the static scene would lose its points
    (docs/evaluation.md). `grads`: `gradients(grey)`, or them stacked (H, W, 2), where the caller
    has them already."""
    X = visible_points(scan, T_cam_velo, K, grey.shape, cfg)
    if not len(X):
        return X
    if not isinstance(grads, np.ndarray):
        grads = cv2.merge(gradients(grey) if grads is None else grads)  # (H, W, 2), faster than np.dstack
    g = bilinear(grads, project(X, K)[0])
    mag = np.hypot(g[:, 0], g[:, 1])
    keep = mag > cfg.min_gradient
    X = X[keep]
    if len(X) > cfg.capacity:  # evenly spaced in scan order, so spread over the whole view
        X = X[np.linspace(0, len(X) - 1, cfg.capacity).round().astype(np.int64)]
    return X


def pad_points(X: np.ndarray, capacity: int) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) -> (1, capacity, 3) float32 points and (1, capacity) float32 mask (1 = a point)."""
    if len(X) > capacity:
        raise ValueError(f"{len(X)} points do not fit a list of {capacity}")
    pts = np.zeros((1, capacity, 3), np.float32)
    pts[0, :, 2] = 1.0  # padding sits 1 m ahead of the camera: finite in every formula, masked out
    pts[0, : len(X)] = X
    mask = np.zeros((1, capacity), np.float32)
    mask[0, : len(X)] = 1.0
    return pts, mask


def point_config(model_config: dict) -> PointConfig:
    """The selection a point-solver model was built for (its manifest's or checkpoint's config)."""
    return PointConfig(min_gradient=model_config["pt_min_gradient"], min_depth=model_config["min_depth"],
                       max_depth=model_config["max_depth"], capacity=model_config["pt_capacity"])


def solver_pyramid(grey: np.ndarray, levels: int, finest: np.ndarray | None = None) -> list[np.ndarray]:
    """Finest first: (3, h, w) float32 grey, d/du, d/dv at `levels` pyrDown levels, level 0 the
    image itself; what `models.point_solver.image_pyramids` computes in torch. Made once per frame
    (frame t's is frame t-1's at the next pair), beside the network in a pipeline, instead of in
    the graph at every pair. `finest`: level 0 already made (grey and `gradients`), where the
    caller has it. Each image is written into its level in place: no stacking copies."""
    out = []
    for k in range(levels):
        if k == 0 and finest is not None:
            out.append(finest)
            continue
        h, w = grey.shape if k == 0 else ((out[-1].shape[1] + 1) // 2, (out[-1].shape[2] + 1) // 2)
        level = np.empty((3, h, w), np.float32)
        if k:
            cv2.pyrDown(out[-1][0], dst=level[0])
        else:
            level[0] = grey
        gradients(level[0], out=level[1:])
        out.append(level)
    return out


@dataclass
class SolverFrame:
    """What the point solver needs of one frame: its grey image and its textured LiDAR points, and
    for a graph that takes them, its image pyramid."""
    grey: np.ndarray  # (H, W) float32 in [0, 1], the camera's full resolution
    points: np.ndarray  # (M, 3) image_2 camera coordinates
    pyramid: list[np.ndarray] | None = None  # `solver_pyramid(grey, levels)`
    # (H, W) metres of the frame's own LiDAR returns, 0 where none: for a graph that reads frame t's
    # scan (`SCAN_DEPTH_INPUT`)
    depth: np.ndarray | None = None

    @classmethod
    def of(cls, image: np.ndarray, scan: np.ndarray, T_cam_velo: np.ndarray, K: np.ndarray,
           cfg: PointConfig, levels: int = 0, depth_P: np.ndarray | None = None) -> "SolverFrame":
        """depth_P: the 3x4 LiDAR-to-pixel matrix where the graph takes the frame's LiDAR depth."""
        stack = finest_level(image)
        points = textured_points(scan, T_cam_velo, K, stack[0], cfg, (stack[1], stack[2]))
        depth = None if depth_P is None else sparse_depth(scan, depth_P, image.shape[1], image.shape[0])
        return cls.assemble(stack, points, levels, depth)

    @classmethod
    def assemble(cls, stack: np.ndarray, points: np.ndarray, levels: int, depth: np.ndarray | None) -> "SolverFrame":
        """The frame from its finest level (`finest_level`), its textured points and its LiDAR depth
        (where the graph takes it)."""
        return cls(stack[0], points, solver_pyramid(stack[0], levels, stack) if levels else None, depth)


def finest_level(image: np.ndarray) -> np.ndarray:
    """(3, H, W) float32: the camera image's grey in [0, 1] and its d/du, d/dv (`gradients`), the
    solver pyramid's finest level, from which `textured_points` picks the points."""
    stack = np.empty((3, *image.shape[:2]), np.float32)
    gradients(grey_image(image, stack[0]), stack[1:])
    return stack


def solver_feeds(prev: SolverFrame, cur: SolverFrame, K: np.ndarray, capacity: int) -> dict[str, np.ndarray]:
    """The flow+pose graph's point-solver inputs for the pair (prev, cur); K: image_2's 3x3. With
    pyramids, both frames' levels (`image1_pK` frame t-1's grey, `stack2_pK` frame t's grey and
    derivatives); the grey images themselves for graphs that build their own pyramids."""
    pts, mask = pad_points(prev.points, capacity)
    feeds = {"image1": prev.grey[None, None], "image2": cur.grey[None, None], "points1": pts, "point_mask1": mask,
             "image_intrinsics": np.array([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]]], np.float32)}
    if prev.pyramid is not None and cur.pyramid is not None:
        for k, (a, b) in enumerate(zip(prev.pyramid, cur.pyramid)):
            feeds[f"image1_p{k}"], feeds[f"stack2_p{k}"] = a[None, :1], b[None]
    if cur.depth is not None:
        feeds[SCAN_DEPTH_INPUT] = cur.depth[None, None]
    return feeds
