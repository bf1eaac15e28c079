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


@pytest.mark.parametrize("depth_input", ["sparse", "ipbasic"])
def test_invdepth_input_is_inverse_depth(small_synth, depth_input):
    seq = KittiSequence.open(small_synth)
    pre = _pre(seq, depth_input)
    metres = pre.depth(seq.scan(1))
    assert (metres > 0).mean() > (0.5 if depth_input == "ipbasic" else 0.01)  # not a vacuous comparison
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
