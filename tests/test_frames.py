"""The runtime's preprocessing makes exactly the inputs the deployed graphs are exported with:
the model's own normalisation and inverse depth, computed by torch as the reference."""

import numpy as np
import pytest
import torch

from d3lvo_deploy.frames import FramePreprocessor
from d3lvo_deploy.sequence import KittiSequence
from models.config import D3LVOConfig
from models.d3lvo import D3LVO
from models.layers import inverse_depth

CFG = D3LVOConfig.small(height=64, width=224)


def _pre(seq: KittiSequence, depth_input: str) -> FramePreprocessor:
    h, w = seq.image(0).shape[:2]
    return FramePreprocessor.for_model(seq.calib, w, h, CFG.to_dict(), depth_input)


def test_rgb_input_is_the_models_normalisation(small_synth):
    seq = KittiSequence.open(small_synth)
    pre = _pre(seq, "sparse")
    img = seq.image(1)
    rgb01 = torch.from_numpy(pre.rgb(img)).permute(2, 0, 1)[None]  # the training path
    ref = D3LVO(CFG).normalise(rgb01)
    got = pre.rgb_input(img)
    assert got.shape == (1, 3, CFG.height, CFG.width) and got.dtype == np.float32
    np.testing.assert_allclose(got, ref.numpy(), rtol=0, atol=2e-6)


def test_sparse_invdepth_input_by_hand(small_synth):
    """Each return placed by the test's own geometry, not the runtime's projection: LiDAR -> cam0
    by Tr, cam0 -> cam2 by the translation b = K2^-1 P2[:, 3], the pinhole K2, then the crop and
    resize as pixel centres map ((u + 0.5 - left) * scale - 0.5); the nearest return per pixel
    gives min_depth / depth. A projection that dropped P2's baseline column moves most pixels."""
    seq = KittiSequence.open(small_synth)
    pre = _pre(seq, "sparse")
    scan = seq.scan(1)
    K2 = seq.calib.P2[:, :3]
    b = np.linalg.solve(K2, seq.calib.P2[:, 3])
    X = (scan[:, :3].astype(np.float64) @ seq.calib.Tr[:3, :3].T + seq.calib.Tr[:3, 3]) + b
    z = X[:, 2]
    X, z = X[z > 0.1], z[z > 0.1]
    u, v = K2[0, 0] * X[:, 0] / z + K2[0, 2], K2[1, 1] * X[:, 1] / z + K2[1, 2]
    view = pre.view
    sx, sy = view.width / view.crop_width, view.height / view.crop_height
    col = np.floor((u + 0.5 - view.left) * sx - 0.5 + 0.5).astype(int)
    row = np.floor((v + 0.5 - view.top) * sy - 0.5 + 0.5).astype(int)
    expected = np.zeros((view.height, view.width))
    for c, r, d in zip(col, row, z):
        if 0 <= c < view.width and 0 <= r < view.height:
            expected[r, c] = max(expected[r, c], CFG.min_depth / max(d, CFG.min_depth))
    got = pre.invdepth_input(scan)[0, 0]
    assert (expected > 0).sum() > 500
    same = np.isclose(got, expected, rtol=1e-5, atol=0)
    # a return exactly on a pixel border may round the other way in float32: a handful at most
    assert same.mean() > 0.999, (same.size - same.sum(), same.size)


def test_ipbasic_invdepth_input_is_inverse_depth(small_synth):
    """IP-Basic's metres enter the graph as the model's inverse depth (torch's formula)."""
    seq = KittiSequence.open(small_synth)
    pre = _pre(seq, "ipbasic")
    metres = pre.depth(seq.scan(1))
    assert (metres > 0).mean() > 0.5  # not a vacuous comparison
    ref = inverse_depth(torch.from_numpy(metres)[None, None], CFG.min_depth).numpy()
    np.testing.assert_array_equal(pre.invdepth_input(seq.scan(1)), ref)


def test_no_depth_input_in_rgb_mode(small_synth):
    seq = KittiSequence.open(small_synth)
    assert _pre(seq, "none").invdepth_input(seq.scan(0)) is None


def test_training_preprocessor_refuses_deployed_inputs(small_synth):
    seq = KittiSequence.open(small_synth)
    h, w = seq.image(0).shape[:2]
    pre = FramePreprocessor.create(seq.calib, w, h, CFG.width, CFG.height, "sparse")
    with pytest.raises(ValueError, match="for_model"):
        pre.rgb_input(seq.image(0))
