"""The paper's augmentations (Sec. IV-B) with the relative pose transformed to match.

Every image operation is a change of camera frame C (x_new = C x_old), so a relative motion A
(frame t in frame t-1 coordinates) becomes C A C^-1: a horizontal flip is C = diag(-1, 1, 1),
a rotation of the image by `angle` about the principal point is a roll about the optical axis.
"""

from __future__ import annotations

import cv2
import numpy as np


def conjugate(A: np.ndarray, C3: np.ndarray) -> np.ndarray:
    C = np.eye(4)
    C[:3, :3] = C3
    return C @ A @ np.linalg.inv(C)


FLIP = np.diag([-1.0, 1.0, 1.0])


def flip_pose(A: np.ndarray) -> np.ndarray:
    return conjugate(A, FLIP)


def roll_matrix(angle_deg: float) -> np.ndarray:
    """The camera-frame rotation that cv2.getRotationMatrix2D(c, angle_deg, 1) applies to pixels."""
    a = np.radians(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def roll_pose(A: np.ndarray, angle_deg: float) -> np.ndarray:
    return conjugate(A, roll_matrix(angle_deg))


def flip_images(*arrays: np.ndarray) -> list[np.ndarray]:
    return [np.ascontiguousarray(a[:, ::-1]) for a in arrays]


def rotate_images(images: list[np.ndarray], depths: list[np.ndarray], angle_deg: float,
                  centre: tuple[float, float]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Rotate about the principal point; images bilinear, depth maps nearest (no blended holes)."""
    M = cv2.getRotationMatrix2D(centre, angle_deg, 1.0)
    h, w = images[0].shape[:2]
    imgs = [cv2.warpAffine(i, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT) for i in images]
    deps = [cv2.warpAffine(d, M, (w, h), flags=cv2.INTER_NEAREST, borderValue=0) for d in depths]
    return imgs, deps
