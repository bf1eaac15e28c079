"""LiDAR -> sparse depth in image_2 at the network's resolution.

KITTI images are ~1241x376 and vary by sequence; the network takes a bottom-centre crop
(1216x352 in the paper, the KITTI depth-completion convention: the sky rows at the top carry no
LiDAR), optionally resized by `scale` for reduced-resolution models. The same `View` maps the
image and the intrinsics, so depth and pixels stay registered.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class View:
    """A bottom-centre crop of the source image, then a resize to (width, height)."""

    src_width: int
    src_height: int
    top: int
    left: int
    crop_width: int
    crop_height: int
    width: int
    height: int

    @property
    def scale(self) -> float:
        return self.width / self.crop_width

    @property
    def affine(self) -> np.ndarray:
        """3x3 map from source pixel coordinates to network pixel coordinates.

        Pixel centres sit at integers, so a resize maps x -> (x + 0.5) * s - 0.5, as cv2.resize does.
        """
        sx = self.width / self.crop_width
        sy = self.height / self.crop_height
        return np.array([
            [sx, 0, (0.5 - self.left) * sx - 0.5],
            [0, sy, (0.5 - self.top) * sy - 0.5],
            [0, 0, 1.0],
        ])

    def project_matrix(self, P: np.ndarray) -> np.ndarray:
        """Adjust a 3x4 projection (or 3x3 intrinsics) for the crop and scale."""
        return self.affine @ np.asarray(P, dtype=np.float64)

    def apply_image(self, image: np.ndarray) -> np.ndarray:
        crop = image[self.top : self.top + self.crop_height, self.left : self.left + self.crop_width]
        if (self.width, self.height) == (self.crop_width, self.crop_height):
            return np.ascontiguousarray(crop)
        return cv2.resize(crop, (self.width, self.height), interpolation=cv2.INTER_AREA)


    def apply_depth(self, depth: np.ndarray) -> np.ndarray:
        """Depth maps resize with nearest neighbour: averaging would blend holes and edges."""
        crop = depth[self.top : self.top + self.crop_height, self.left : self.left + self.crop_width]
        if (self.width, self.height) == (self.crop_width, self.crop_height):
            return np.ascontiguousarray(crop)
        return cv2.resize(crop, (self.width, self.height), interpolation=cv2.INTER_NEAREST)


def bottom_center_view(src_width: int, src_height: int, crop_width: int = 1216, crop_height: int = 352,
                       scale: float = 1.0) -> View:
    """The paper's crop; raises if the image is smaller than the crop."""
    if src_width < crop_width or src_height < crop_height:
        raise ValueError(f"image {src_width}x{src_height} is smaller than the {crop_width}x{crop_height} crop")
    return View(src_width, src_height, src_height - crop_height, (src_width - crop_width) // 2,
                crop_width, crop_height, int(round(crop_width * scale)), int(round(crop_height * scale)))


PAPER_CROP = (1216, 352)


def network_view(src_width: int, src_height: int, net_width: int, net_height: int) -> View:
    """How a source image becomes the network input.

    The paper's rule when it applies: bottom-centre 1216x352 crop, then resize to the network
    size (same aspect). Otherwise (small or odd images) the largest bottom-centre crop with the
    network's aspect ratio, resized to it.
    """
    cw, ch = PAPER_CROP
    if src_width >= cw and src_height >= ch and net_width * ch == net_height * cw:
        v = bottom_center_view(src_width, src_height, cw, ch)
        return View(v.src_width, v.src_height, v.top, v.left, cw, ch, net_width, net_height)
    cw = min(src_width, int(src_height * net_width / net_height))
    ch = min(src_height, int(round(cw * net_height / net_width)))
    v = bottom_center_view(src_width, src_height, cw, ch)
    return View(v.src_width, v.src_height, v.top, v.left, cw, ch, net_width, net_height)


PROJECTION_MIN_DEPTH = 0.1  # m: the nearest depth a projection keeps unless told otherwise


def rows_in_depth(points: np.ndarray, depth_row: np.ndarray, min_depth: float,
                  max_depth: float = np.inf) -> np.ndarray:
    """The rows of an (N, >=3) float32 scan whose depth (`depth_row` . (x, y, z, 1)) may lie in
    (min_depth, max_depth): computed in float32 with a centimetre's margin, so that no row the
    float64 depth keeps is dropped, and only those rows go on to float64. Picked with np.compress
    on whole rows, ten times faster than a boolean index or np.compress on a column slice."""
    r = np.asarray(depth_row, np.float32)
    z = points[:, :3] @ r[:3] + r[3]
    return np.compress((z > min_depth - 0.01) & (z < max_depth + 0.01), points, axis=0)


def rows_in_view(points: np.ndarray, P: np.ndarray, width: int, height: int, min_depth: float,
                 margin: float = 16.0) -> np.ndarray:
    """The rows of an (N, >=3) float32 scan that may land in a width x height image under the 3x4
    P (LiDAR to pixels) at a depth above min_depth: three float32 dot products per row and one
    np.compress on whole rows, so that each later pass (the network's sparse depth, the solver's
    points, in float64) sees the part of a 360-degree scan the camera can see (15-19 %) instead
    of the half ahead of it. Conservative by `margin` pixels and a centimetre of depth: every row a
    later pass keeps stays, in scan order."""
    Pf = np.asarray(P, np.float32)
    W = np.zeros((3, points.shape[1]), np.float32)
    W[:, :3] = Pf[:, :3]
    # (3, N) rows u z, v z, z: a GEMM on the whole rows and row-wise adds, ten times faster than
    # adding the offsets to an (N, 3) product
    uz, vz, z = W @ points.T + Pf[:, 3:]
    lo = np.float32(-margin) * z
    keep = ((z > min_depth - 0.01) & (uz >= lo) & (uz <= np.float32(width - 1 + margin) * z)
            & (vz >= lo) & (vz <= np.float32(height - 1 + margin) * z))
    return np.compress(keep, points, axis=0)


def project_points(points: np.ndarray, P: np.ndarray, width: int, height: int,
                   min_depth: float = PROJECTION_MIN_DEPTH) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project (N,>=3) LiDAR points with a 3x4 P; returns in-image pixel cols, rows and depths.

    Pixel (r, c) covers [c-0.5, c+0.5) x [r-0.5, r+0.5): KITTI puts pixel centres at integers.
    Depth is computed first so that u, v are only computed for the ~half of a scan in front; a
    float32 scan is converted to float64 only there.
    """
    pts = np.asarray(points)
    P = np.asarray(P, dtype=np.float64)
    if pts.dtype != np.float64:
        pts = rows_in_depth(pts, P[2], min_depth)
    xyz = pts[:, :3].astype(np.float64)
    z = xyz @ P[2, :3] + P[2, 3]
    front = z > min_depth  # np.compress: ten times faster than a boolean index on these arrays
    xyz, z = np.compress(front, xyz, axis=0), z[front]
    uv = xyz @ P[:2, :3].T + P[:2, 3]
    c = np.floor(uv[:, 0] / z + 0.5).astype(np.int64)
    r = np.floor(uv[:, 1] / z + 0.5).astype(np.int64)
    inside = (c >= 0) & (c < width) & (r >= 0) & (r < height)
    return c[inside], r[inside], z[inside]


def sparse_depth(points: np.ndarray, P: np.ndarray, width: int, height: int,
                 min_depth: float = PROJECTION_MIN_DEPTH) -> np.ndarray:
    """(H,W) float32 depth in metres, 0 where no point landed; the nearest point wins a pixel."""
    c, r, z = project_points(points, P, width, height, min_depth)
    depth = np.full(height * width, np.inf, dtype=np.float32)
    # float32 rounding is monotonic, so the minimum of the rounded depths is the nearest point's
    np.minimum.at(depth, r * width + c, z.astype(np.float32))
    depth[depth == np.inf] = 0.0
    return depth.reshape(height, width)


def sparse_inverse_depth(points: np.ndarray, P: np.ndarray, width: int, height: int, scale: float,
                         min_depth: float = PROJECTION_MIN_DEPTH) -> np.ndarray:
    """(H,W) float32 scale / max(d, scale) of the nearest point per pixel, 0 where none landed.

    Equal to that formula applied to `sparse_depth` (the map is monotonic, so the nearest point
    has the largest value), but computed on the points alone: no full-image passes."""
    c, r, z = project_points(points, P, width, height, min_depth)
    s = np.float32(scale)
    inv = np.zeros(height * width, dtype=np.float32)
    np.maximum.at(inv, r * width + c, s / np.maximum(z.astype(np.float32), s))
    return inv.reshape(height, width)
