"""Pictures of what the network sees, drawn with OpenCV (no plotting library on the vehicle).

One PNG panel per frame: the camera image, the projected LiDAR depth, the completed depth, the
finest flow in the usual HSV coding (hue = direction, saturation = magnitude) and the per-pixel
confidence of the Gauss-Newton pose step, each with its colour bar.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

BAR = 36  # height of the label + colour bar strip, pixels


def flow_to_rgb(flow: np.ndarray, max_mag: float | None = None) -> np.ndarray:
    """(2,h,w) flow -> (h,w,3) uint8 RGB; hue = direction, saturation = |flow| / max_mag."""
    fx, fy = flow[0].astype(np.float32), flow[1].astype(np.float32)
    mag, ang = cv2.cartToPolar(fx, fy, angleInDegrees=True)
    top = float(max_mag if max_mag else max(np.percentile(mag, 99), 1e-6))
    hsv = np.empty(flow.shape[1:] + (3,), np.uint8)
    hsv[..., 0] = (ang / 2).astype(np.uint8)  # OpenCV hue is 0..179
    hsv[..., 1] = np.clip(mag / top * 255, 0, 255).astype(np.uint8)
    hsv[..., 2] = 255
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)


def colourise(x: np.ndarray, lo: float, hi: float, valid: np.ndarray | None = None) -> np.ndarray:
    """Scalar map -> RGB with the turbo colour map over [lo, hi]; black where not valid."""
    u8 = np.clip((x - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(u8, cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    if valid is not None:
        rgb[~valid] = 0
    return rgb


def _strip(width: int, label: str, lo: str, hi: str, bar: np.ndarray | None) -> np.ndarray:
    s = np.full((BAR, width, 3), 255, np.uint8)
    cv2.putText(s, label, (6, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    if bar is not None:
        x0, x1 = width // 2, width - 60
        s[20:32, x0:x1] = cv2.resize(bar, (x1 - x0, 12), interpolation=cv2.INTER_NEAREST)
        cv2.putText(s, lo, (x0 - 8 - 7 * len(lo), 31), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(s, hi, (x1 + 6, 31), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return s


def _ramp(lo: float, hi: float) -> np.ndarray:
    return colourise(np.linspace(lo, hi, 256)[None, :], lo, hi)


def network_view(last: dict, to_metres, completed: bool) -> dict:
    """One frame's kept tensors (`Odometry.last`) as what the pictures show: the camera image,
    LiDAR and completed depth in metres (`to_metres`: StageModel.dense_depth_m), the finest flow
    (2,h,w) and the finest Gauss-Newton confidence (h,w); None where the model has none."""
    out = last.get("flowpose", {})
    finest = lambda prefix: min((k for k in out if k.startswith(prefix)), key=lambda k: int(k[len(prefix):]),  # noqa: E731
                                default=None)
    flow, conf = finest("flow_l"), finest("confidence_l")
    return {"image": last["image"], "lidar_m": to_metres(last["sparse_invdepth"])[0, 0],
            "dense_m": to_metres(last["dense_invdepth"])[0, 0] if completed else None,
            "flow": None if flow is None else out[flow][0], "confidence": None if conf is None else out[conf][0, 0],
            # the point head's confidence is 1 - p(moves on its own), in (0, 1); the cell head's in (0, 2)
            "points_head": "point_weights" in out}


def frame_panel(image: np.ndarray, sparse_m: np.ndarray, dense_m: np.ndarray | None, flow: np.ndarray | None,
                confidence: np.ndarray | None, max_depth: float = 80.0, points_head: bool = False) -> np.ndarray:
    """Rows of equal width (the network view's): image, LiDAR depth, completed depth, flow,
    confidence; each with a label and colour bar. Depth in metres (0 = none), flow (2,h,w) in
    cells of its level, confidence (h,w) of the finest Gauss-Newton level."""
    h, w = sparse_m.shape
    up = lambda x, interp=cv2.INTER_NEAREST: cv2.resize(x, (w, h), interpolation=interp)  # noqa: E731
    rows = [_strip(w, "camera (network view)", "", "", None), up(image, cv2.INTER_AREA)]
    # LiDAR returns are single pixels: dilate so that they can be seen at this size
    sp = cv2.dilate(sparse_m, np.ones((2, 2), np.uint8))
    rows += [_strip(w, "LiDAR depth (projected)", "0 m", f"{max_depth:.0f} m", _ramp(0, max_depth)),
             colourise(sp, 0, max_depth, sp > 0)]
    if dense_m is not None:
        rows += [_strip(w, "completed depth", "0 m", f"{max_depth:.0f} m", _ramp(0, max_depth)),
                 colourise(dense_m, 0, max_depth)]
    if flow is not None:
        mag = float(max(np.percentile(np.hypot(flow[0], flow[1]), 99), 1e-6))
        wheel = flow_to_rgb(np.stack(np.meshgrid(np.linspace(-1, 1, 64), np.zeros(1))), 1.0)
        rows += [_strip(w, f"flow (finest level, HSV: hue = direction, saturation up to {mag:.1f} cells)",
                        "left", "right", wheel), up(flow_to_rgb(flow, mag), cv2.INTER_LINEAR)]
    if confidence is not None and points_head:
        rows += [_strip(w, "confidence that it does not move (the LiDAR points' weights)", "0", "1", _ramp(0, 1)),
                 up(colourise(confidence, 0.0, 1.0), cv2.INTER_NEAREST)]
    elif confidence is not None:
        rows += [_strip(w, "pose confidence (finest Gauss-Newton level; 1 = initial)", "0", "2", _ramp(0, 2)),
                 up(colourise(confidence, 0.0, 2.0), cv2.INTER_NEAREST)]
    return np.concatenate(rows, 0)


def write_panel(path: str | Path, panel: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(panel, cv2.COLOR_RGB2BGR)):
        raise OSError(f"cannot write {path}")
    return path
