"""SE(3)/SO(3) as pure numpy functions on 4x4 / 3x3 arrays (leading batch dimensions allowed).

Quaternions are (w, x, y, z) unless ``scalar_first=False`` (TUM files store x, y, z, w).
q and -q are the same rotation: converters accept either and `rot_to_quat` returns w >= 0.
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def make_se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def se3_inv(T: np.ndarray) -> np.ndarray:
    """Closed-form inverse: exact for rigid motions and cheaper than a general inverse."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    t = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    return make_se3(Rt, t)


def compose(*Ts: np.ndarray) -> np.ndarray:
    out = np.asarray(Ts[0], dtype=np.float64)
    for T in Ts[1:]:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def relative(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """Motion from pose a to pose b, expressed in a's frame: inv(T_a) @ T_b."""
    return se3_inv(T_a) @ np.asarray(T_b, dtype=np.float64)


def relatives(poses: np.ndarray) -> np.ndarray:
    """(N,4,4) absolute poses -> (N-1,4,4) frame-to-frame motions."""
    poses = np.asarray(poses, dtype=np.float64)
    return relative(poses[:-1], poses[1:])


def accumulate(rel: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """Chain (N,4,4) relative motions into N+1 absolute poses starting at `start` (identity)."""
    rel = np.asarray(rel, dtype=np.float64).reshape(-1, 4, 4)
    out = np.empty((len(rel) + 1, 4, 4))
    out[0] = np.eye(4) if start is None else start
    for i, T in enumerate(rel):
        out[i + 1] = out[i] @ T
    return out


def change_frame(T_rel: np.ndarray, T_b_a: np.ndarray) -> np.ndarray:
    """Express a motion given in frame a in a rigidly attached frame b: T_b_a @ T_rel @ inv(T_b_a)."""
    return np.asarray(T_b_a) @ np.asarray(T_rel) @ se3_inv(T_b_a)


def is_rigid(T: np.ndarray, atol: float = 1e-3) -> bool:
    """A 4x4 whose last row is 0 0 0 1 and whose rotation block is orthonormal to `atol`."""
    return bool(np.allclose(T[3], [0, 0, 0, 1]) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=atol))


def skew(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def quat_to_rot(q: np.ndarray, scalar_first: bool = True) -> np.ndarray:
    """Unit or non-unit quaternion (either sign) -> rotation matrix."""
    q = np.asarray(q, dtype=np.float64)
    if not scalar_first:
        q = np.concatenate([q[..., 3:4], q[..., :3]], -1)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < _EPS):
        raise ValueError("zero-norm quaternion")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rot_to_quat(R: np.ndarray, scalar_first: bool = True) -> np.ndarray:
    """Rotation matrix -> unit quaternion with w >= 0 (Shepperd's method, stable for all angles)."""
    R = np.asarray(R, dtype=np.float64)
    batch = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    tr = np.trace(R, axis1=1, axis2=2)
    diag = np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], 1)
    k = np.argmax(diag, axis=1)
    q = np.empty((len(R), 4))
    for i in range(len(R)):
        m = R[i]
        if k[i] == 0:
            s = 2.0 * np.sqrt(max(1.0 + tr[i], _EPS))
            q[i] = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif k[i] == 1:
            s = 2.0 * np.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], _EPS))
            q[i] = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif k[i] == 2:
            s = 2.0 * np.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], _EPS))
            q[i] = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], _EPS))
            q[i] = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    if not scalar_first:
        q = np.concatenate([q[:, 1:], q[:, :1]], 1)
    return q.reshape(batch + (4,))


def quat_canonical(q: np.ndarray) -> np.ndarray:
    """Normalise and pick the w >= 0 representative of {q, -q}."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def axis_angle_to_rot(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula; rvec = axis * angle (radians)."""
    rvec = np.asarray(rvec, dtype=np.float64)
    theta = np.linalg.norm(rvec, axis=-1)[..., None, None]
    K = skew(rvec)
    small = theta < 1e-8
    th = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(th) / th)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(th)) / th**2)
    return np.eye(3) + a * K + b * (K @ K)


def rot_to_axis_angle(R: np.ndarray) -> np.ndarray:
    """Inverse of `axis_angle_to_rot`, via the quaternion so angles near pi stay accurate."""
    q = rot_to_quat(R)
    w = np.clip(q[..., 0], -1.0, 1.0)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    scale = np.where(s < 1e-12, 2.0, angle / np.maximum(s, 1e-300))
    return v * scale[..., None]


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle of a rotation (radians) as the KITTI devkit computes it: acos(clamp((tr-1)/2))."""
    R = np.asarray(R, dtype=np.float64)
    d = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)
    return np.arccos(np.clip(d, -1.0, 1.0))


def rotation_angle_precise(R: np.ndarray) -> np.ndarray:
    """Angle via atan2(|axis part|, cos part): accurate for tiny angles, where acos is not."""
    R = np.asarray(R, dtype=np.float64)
    c = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    return np.arctan2(0.5 * np.linalg.norm(v, axis=-1), c)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares (R, t, s) with dst ~ s R src + t (Umeyama 1991). src, dst: (N,3)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError("umeyama needs two (N,3) arrays of equal shape")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > _EPS else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def apply_sim3(poses: np.ndarray, R: np.ndarray, t: np.ndarray, s: float) -> np.ndarray:
    """Map a trajectory by x -> s R x + t; orientations rotate by R, positions scale by s."""
    out = np.array(poses, dtype=np.float64, copy=True)
    out[..., :3, :3] = R @ out[..., :3, :3]
    out[..., :3, 3] = s * np.einsum("ij,...j->...i", R, out[..., :3, 3]) + t
    return out
