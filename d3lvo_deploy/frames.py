"""One frame (image + LiDAR scan) -> network inputs. Shared by training and the runtime, so the
network sees on the vehicle exactly what it saw in training.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .calib import Calib
from .ipbasic import fill_in_fast
from .projection import View, network_view, sparse_depth


@dataclass
class FramePreprocessor:
    calib: Calib
    view: View
    depth_input: str  # none | sparse | ipbasic
    max_depth: float = 120.0

    @classmethod
    def create(cls, calib: Calib, image_width: int, image_height: int, net_width: int, net_height: int,
               depth_input: str, max_depth: float = 120.0) -> "FramePreprocessor":
        return cls(calib, network_view(image_width, image_height, net_width, net_height), depth_input, max_depth)

    @property
    def P(self) -> np.ndarray:
        return self.view.project_matrix(self.calib.P_velo_to_image2)

    @property
    def K(self) -> np.ndarray:
        return self.view.project_matrix(self.calib.K2)

    def rgb(self, image: np.ndarray) -> np.ndarray:
        """(H,W,3) uint8 RGB -> (h,w,3) float32 in [0,1] at the network resolution."""
        return self.view.apply_image(image).astype(np.float32) / 255.0

    def rgb_nchw(self, image: np.ndarray) -> np.ndarray:
        """The same values as `rgb`, as the (1,3,h,w) network input in one pass (runtime path)."""
        crop = self.view.apply_image(image)
        out = np.empty((1, 3) + crop.shape[:2], np.float32)
        np.divide(crop.transpose(2, 0, 1), np.float32(255.0), out=out[0])
        return out

    def depth(self, points: np.ndarray | None) -> np.ndarray:
        """(N,4) scan -> (h,w) float32 metres: sparse, IP-Basic dense, or zeros (rgb mode)."""
        if self.depth_input == "none" or points is None:
            return np.zeros((self.view.height, self.view.width), np.float32)
        d = sparse_depth(points, self.P, self.view.width, self.view.height)
        if self.depth_input == "ipbasic":
            d = fill_in_fast(d, max_depth=self.max_depth)
        return d
