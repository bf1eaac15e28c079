"""One frame (image + LiDAR scan) -> network inputs. Shared by training and the runtime, so the
network sees on the vehicle exactly what it saw in training.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .calib import Calib
from .ipbasic import fill_in_fast
from .projection import View, network_view, sparse_depth, sparse_inverse_depth


@dataclass
class FramePreprocessor:
    calib: Calib
    view: View
    depth_input: str  # none | sparse | ipbasic
    max_depth: float = 120.0
    # for the deployed graphs' inputs (`rgb_input`, `invdepth_input`); training uses `rgb`/`depth`
    min_depth: float | None = None
    rgb_mean: tuple[float, float, float] | None = None
    rgb_std: tuple[float, float, float] | None = None

    @classmethod
    def create(cls, calib: Calib, image_width: int, image_height: int, net_width: int, net_height: int,
               depth_input: str, max_depth: float = 120.0) -> "FramePreprocessor":
        return cls(calib, network_view(image_width, image_height, net_width, net_height), depth_input, max_depth)

    @classmethod
    def for_model(cls, calib: Calib, image_width: int, image_height: int, config: dict,
                  depth_input: str) -> "FramePreprocessor":
        """For an exported model: `config` is its manifest's `model_config` (D3LVOConfig.to_dict())."""
        return cls(calib, network_view(image_width, image_height, config["width"], config["height"]), depth_input,
                   config["max_depth"], config["min_depth"], tuple(config["rgb_mean"]), tuple(config["rgb_std"]))

    @property
    def P(self) -> np.ndarray:
        return self.view.project_matrix(self.calib.P_velo_to_image2)

    @property
    def K(self) -> np.ndarray:
        return self.view.project_matrix(self.calib.K2)

    def rgb(self, image: np.ndarray) -> np.ndarray:
        """(H,W,3) uint8 RGB -> (h,w,3) float32 in [0,1] at the network resolution."""
        return self.view.apply_image(image).astype(np.float32) / 255.0

    def rgb_input(self, image: np.ndarray) -> np.ndarray:
        """(H,W,3) uint8 RGB -> (1,3,h,w) float32 ImageNet-normalised, the deployed graphs' RGB input.

        (x / 255 - mean) / std as one multiply-add per channel during the NCHW copy, so the graphs
        do not normalise a full-resolution image in each of two stages."""
        if self.rgb_mean is None or self.rgb_std is None:
            raise ValueError("FramePreprocessor.for_model(...) sets the normalisation this needs")
        std = np.asarray(self.rgb_std, np.float32)
        scale = (1.0 / (255.0 * std)).astype(np.float32)[:, None, None]
        offset = (-np.asarray(self.rgb_mean, np.float32) / std).astype(np.float32)[:, None, None]
        crop = self.view.apply_image(image)
        out = np.empty((1, 3) + crop.shape[:2], np.float32)
        np.multiply(crop.transpose(2, 0, 1), scale, out=out[0])
        out[0] += offset
        return out

    def invdepth_input(self, points: np.ndarray | None) -> np.ndarray | None:
        """(N,4) scan -> (1,1,h,w) float32 min_depth / d (0 = no return), the deployed graphs' depth
        input; None in rgb mode. Same formula as models.layers.inverse_depth, in float32."""
        if self.depth_input == "none":
            return None
        if self.min_depth is None:
            raise ValueError("FramePreprocessor.for_model(...) sets the min_depth this needs")
        min_d = np.float32(self.min_depth)
        if self.depth_input == "sparse":
            if points is None:
                return np.zeros((1, 1, self.view.height, self.view.width), np.float32)
            return sparse_inverse_depth(points, self.P, self.view.width, self.view.height, min_d)[None, None]
        d = self.depth(points)  # IP-Basic fills in metres
        inv = np.zeros((1, 1) + d.shape, np.float32)
        np.divide(min_d, np.maximum(d, min_d), out=inv[0, 0], where=d > 0)
        return inv

    def depth(self, points: np.ndarray | None) -> np.ndarray:
        """(N,4) scan -> (h,w) float32 metres: sparse, IP-Basic dense, or zeros (rgb mode)."""
        if self.depth_input == "none" or points is None:
            return np.zeros((self.view.height, self.view.width), np.float32)
        d = sparse_depth(points, self.P, self.view.width, self.view.height)
        if self.depth_input == "ipbasic":
            d = fill_in_fast(d, max_depth=self.max_depth)
        return d
