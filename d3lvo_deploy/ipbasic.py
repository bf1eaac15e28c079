"""IP-Basic depth completion (Ku, Harakeh, Waslander, CRV 2018), the fast default variant.

Classical morphology on inverted depth: no parameters, numpy + OpenCV only, so it can serve as
the `completion=ipbasic` option in training and on the vehicle alike.
"""

from __future__ import annotations

import cv2
import numpy as np

FULL_5 = np.ones((5, 5), np.uint8)
FULL_7 = np.ones((7, 7), np.uint8)
FULL_31 = np.ones((31, 31), np.uint8)
DIAMOND_5 = np.array(
    [[0, 0, 1, 0, 0], [0, 1, 1, 1, 0], [1, 1, 1, 1, 1], [0, 1, 1, 1, 0], [0, 0, 1, 0, 0]], np.uint8
)


def fill_in_fast(sparse: np.ndarray, max_depth: float = 100.0, extrapolate: bool = True) -> np.ndarray:
    """(H,W) metres with 0 = no return -> dense (H,W) metres.

    Inverting (max_depth - d) makes dilation prefer near points, so foreground edges survive.
    `extrapolate` copies the top-most depth of each column upwards (the paper's variant for
    images with sky), so every pixel gets a value.
    """
    d = np.array(sparse, dtype=np.float32, copy=True)
    valid = d > 0.1
    d[valid] = max_depth - d[valid]
    d = cv2.dilate(d, DIAMOND_5)
    d = cv2.morphologyEx(d, cv2.MORPH_CLOSE, FULL_5)
    empty = d < 0.1
    d[empty] = cv2.dilate(d, FULL_7)[empty]
    if extrapolate:
        has = d > 0.1
        top = np.argmax(has, axis=0)
        cols = np.arange(d.shape[1])
        top_val = d[top, cols]
        rows = np.arange(d.shape[0])[:, None]
        fill = (rows < top[None, :]) & has.any(axis=0)[None, :]
        d = np.where(fill, top_val[None, :], d)
        empty = d < 0.1
        d[empty] = cv2.dilate(d, FULL_31)[empty]
    d = cv2.medianBlur(d, 5)
    d = cv2.bilateralFilter(d, 5, 1.5, 2.0)
    valid = d > 0.1
    d[valid] = max_depth - d[valid]
    d[~valid] = 0.0
    return d
