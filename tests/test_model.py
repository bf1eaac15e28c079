"""The D3LVO network: shapes, live gradients, the cost volume against loops, attention equations."""

import numpy as np
import pytest
import torch

from models.attention import ChannelAttention, CrossAttention, SpatialAttention
from models.config import D3LVOConfig
from models.correlation import correlation_slices, correlation_stacked, correlation_tiled, cost_volume, l2_normalise
from models.d3lvo import D3LVO
from models.flow import upsample_flow, warp
from models.layers import adaptive_avg_pool, inverse_depth, resize_like, upsample_bilinear
from models.loss import PoseLoss
from models.pose import pose_to_matrix

torch.manual_seed(0)


def _inputs(cfg, b=1):
    rgb = torch.rand(b, 3, cfg.height, cfg.width)
    depth = torch.rand(b, 1, cfg.height, cfg.width) * 60 * (torch.rand(b, 1, cfg.height, cfg.width) > 0.9)
    return rgb, rgb.roll(3, dims=3), depth, depth.roll(3, dims=3)


@pytest.mark.parametrize("levels", [(3, 2), (3, 2, 1)])
def test_shapes_at_paper_resolution(levels):
    cfg = D3LVOConfig(flow_levels=levels)
    model = D3LVO(cfg).eval()
    with torch.no_grad():
        out = model(*_inputs(cfg))
    expect = {3: (22, 76), 2: (44, 152), 1: (88, 304)}
    assert [tuple(f.shape[-2:]) for f in out["flows"]] == [expect[lvl] for lvl in levels]
    n = len(cfg.gn_levels)  # the Gauss-Newton head adds h/4 after the flow's h/8
    assert cfg.gn_levels == tuple(levels) + ((1,) if levels[-1] > 1 else ())
    assert out["poses"].shape == (1, n, 7) and out["weights"].shape == (1, n)
    assert out["dense1"].shape == (1, 1, 352, 1216)
    assert torch.all(out["dense1"] >= cfg.min_depth) and torch.all(out["dense1"] <= cfg.max_depth)
    torch.testing.assert_close(out["weights"].sum(1), torch.ones(1))
    M = out["matrix"][0]
    torch.testing.assert_close(M[:3, :3] @ M[:3, :3].T, torch.eye(3), atol=1e-5, rtol=0)


@pytest.mark.parametrize("mode, levels", [("rgb", (3, 2, 1, 0)), ("rgb_sparse", (3, 2, 1, 0)),
                                          ("rgb_completion", (3, 2, 1, 0)), ("rgb_completion", (3, 2, 1))])
def test_every_parameter_gets_a_gradient(mode, levels):
    # seeded here: with 4 hidden ReLU units, CA's MLP can start all-dead for an unlucky draw
    # (a property of eq. 1's ReLU at random init, not a disconnected branch)
    torch.manual_seed(0)
    cfg = D3LVOConfig.small(height=64, width=256, mode=mode, flow_levels=levels, xa_levels=(2, 3))
    model = D3LVO(cfg).train()
    loss_fn = PoseLoss()
    out = model(*_inputs(cfg, b=2))
    gt = torch.tensor([[0.1, 0.0, 1.0, 1.0, 0.0, 0.01, 0.0]] * 2)
    loss, _ = loss_fn(out["poses"], out["pose"], gt)
    if "dense1" in out:
        loss = loss + out["dense1"].mean() * 0.01
    # as in training: the flow has its own loss (the Gauss-Newton head reads it only through the
    # confidence's detached flow-vs-rigid disagreement)
    loss = loss + sum(f.abs().mean() for f in out["flows"]) * 0.01
    loss.backward()
    dead = [n for n, p in list(model.named_parameters()) + list(loss_fn.named_parameters())
            if p.grad is None or not torch.any(p.grad != 0)]
    assert not dead, f"no gradient reaches: {dead}"
    if mode == "rgb":
        assert model.completion is None and not any("dep" in n for n, _ in model.encoder.named_parameters())


def _loop_correlation(f1, f2, s):
    b, c, h, w = f1.shape
    out = torch.zeros(b, (2 * s + 1) ** 2, h, w, dtype=torch.float64)
    for y in range(h):
        for x in range(w):
            k = 0
            for dy in range(-s, s + 1):
                for dx in range(-s, s + 1):
                    if 0 <= y + dy < h and 0 <= x + dx < w:
                        out[:, k, y, x] = (f1[:, :, y, x] * f2[:, :, y + dy, x + dx]).sum(1)
                    k += 1
    return out


def test_deployed_inverse_forms_equal_the_metric_forms():
    """complete_inverse/encode_inverse (what is exported) compute what complete/encode (training) do."""
    cfg = D3LVOConfig(height=64, width=128)
    model = D3LVO(cfg).eval()
    rgb, _, depth, _ = _inputs(cfg)
    with torch.no_grad():
        dense_m = model.complete(rgb, depth)
        inv = model.complete_inverse(model.normalise(rgb), inverse_depth(depth, cfg.min_depth))
        torch.testing.assert_close(inverse_depth(dense_m, cfg.min_depth), inv, rtol=1e-5, atol=1e-7)
        f_m, d_m, g_m = model.encode(rgb, dense_m)
        f_i, d_i, g_i = model.encode_inverse(model.normalise(rgb), inv)
    for a, b in zip(f_m + d_m + g_m, f_i + d_i + g_i):
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("impl", [correlation_slices, correlation_stacked, correlation_tiled,
                                  lambda a, b, s: correlation_tiled(a, b, s, tile=4)])
@pytest.mark.parametrize("hw", [(7, 11), (5, 16), (9, 37)])  # width below, at and across tile sizes
def test_correlation_matches_loops(impl, hw):
    f1 = torch.randn(2, 5, *hw, dtype=torch.float64)
    f2 = torch.randn(2, 5, *hw, dtype=torch.float64)
    torch.testing.assert_close(impl(f1, f2, 4), _loop_correlation(f1, f2, 4))
    torch.testing.assert_close(impl(f1, f2, 2), _loop_correlation(f1, f2, 2))
    assert impl(f1, f2, 4).shape[1] == 81


def test_cost_volume_is_normalised():
    f = torch.randn(1, 16, 6, 6) * 100
    c = cost_volume(f, f)
    torch.testing.assert_close(c[:, 40], torch.ones(1, 6, 6), atol=1e-5, rtol=0)  # zero displacement: cos = 1
    assert c.abs().max() <= 1 + 1e-5
    torch.testing.assert_close(l2_normalise(f).norm(dim=1), torch.ones(1, 6, 6), atol=1e-5, rtol=0)


def test_warp_shifts_by_the_flow():
    x = torch.arange(40.0).view(1, 1, 5, 8)
    flow = torch.zeros(1, 2, 5, 8)
    flow[:, 0] = 2.0  # sample two pixels to the right
    out = warp(x, flow)
    torch.testing.assert_close(out[..., :6], x[..., 2:])
    assert torch.all(out[..., 7] == 0)  # outside: zeros
    up = upsample_flow(torch.ones(1, 2, 4, 4), (8, 16))
    torch.testing.assert_close(up[:, 0], torch.full((1, 8, 16), 4.0))
    torch.testing.assert_close(up[:, 1], torch.full((1, 8, 16), 2.0))


def test_adaptive_pool_matches_torch_for_uneven_sizes():
    x = torch.randn(2, 3, 11, 38)
    torch.testing.assert_close(adaptive_avg_pool(x, (2, 6)), torch.nn.functional.adaptive_avg_pool2d(x, (2, 6)))


@pytest.mark.parametrize("factor", [2, 3, 4])
def test_upsampling_by_phases_is_bilinear_interpolation(factor):
    """The convolution + pixel-shuffle form against torch's bilinear interpolation (half-pixel
    centres, clamped at the border), and resize_like takes it only for one channel and a whole factor."""
    x = torch.randn(2, 1, 7, 9, dtype=torch.float64)
    ref = torch.nn.functional.interpolate(x, scale_factor=factor, mode="bilinear", align_corners=False)
    torch.testing.assert_close(upsample_bilinear(x, factor), ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(resize_like(x, ref), ref, rtol=0, atol=1e-12)
    # by hand at factor 2: output 1 of a row is 3/4 of input 0 and 1/4 of input 1; output 0 is the border value
    row = torch.tensor([[[[1.0, 5.0]]]], dtype=torch.float64)
    torch.testing.assert_close(upsample_bilinear(row, 2)[0, 0, 0], torch.tensor([1.0, 2.0, 4.0, 5.0], dtype=torch.float64))
    many = torch.randn(1, 3, 5, 6)  # several channels: F.interpolate itself
    torch.testing.assert_close(resize_like(many, torch.zeros(1, 1, 5 * factor, 6 * factor)),
                               torch.nn.functional.interpolate(many, scale_factor=factor, mode="bilinear", align_corners=False))


def test_attention_equations_by_hand():
    x = torch.randn(2, 8, 5, 7)
    ca = ChannelAttention(8, 4)
    gate = torch.sigmoid(ca.w2(torch.relu(ca.w1(torch.cat([x.mean((2, 3)), x.amax((2, 3))], 1)))))
    torch.testing.assert_close(ca(x), x * gate[..., None, None])
    sa = SpatialAttention()
    m = torch.sigmoid(sa.f(torch.cat([x.amax(1, keepdim=True), x.mean(1, keepdim=True)], 1)))
    torch.testing.assert_close(sa(x), x * m)
    xa = CrossAttention(8, 4, 6, 3)
    xd = torch.randn(2, 4, 5, 7)
    # eq. 3 for one query position, written out
    tok = lambda t: t.flatten(2)[0].T  # noqa: E731  (HW, dim)
    qr, kr, vr = tok(xa.q_r(x)), tok(xa.k_r(x)), tok(xa.v_r(x))
    qd, kd, vd = tok(xa.q_d(xd)), tok(xa.k_d(xd)), tok(xa.v_d(xd))
    p = 9
    fused = torch.softmax(qr[p] @ kd.T / np.sqrt(6), 0) @ vd + torch.softmax(qd[p] @ kr.T / np.sqrt(6), 0) @ vr
    expect = xa.out.weight[:, :, 0, 0] @ fused + xa.out.bias
    torch.testing.assert_close(xa(x, xd)[0].flatten(1)[:, p], expect, atol=1e-5, rtol=1e-5)


def test_pose_matrix_from_quaternion():
    s = np.sqrt(0.5)
    M = pose_to_matrix(torch.tensor([1.0, 2.0, 3.0, 2 * s, 0.0, 2 * s, 0.0], dtype=torch.float32))  # unnormalised q: 90 deg about y
    torch.testing.assert_close(M[:3, :3] @ torch.tensor([0.0, 0.0, 1.0]), torch.tensor([1.0, 0.0, 0.0]), atol=1e-6, rtol=0)
    torch.testing.assert_close(M[:3, 3], torch.tensor([1.0, 2.0, 3.0]))


def test_loss_matches_equation_11():
    loss = PoseLoss()
    with torch.no_grad():
        loss.s_t.fill_(0.5)
        loss.s_q.fill_(-1.0)
    gt = torch.tensor([[0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]])
    pred = torch.tensor([[0.1, -0.2, 1.3, -2.0, 0.0, 0.0, 0.0]])  # q = -2 * identity: same rotation
    expect = 0.6 * np.exp(-0.5) + 0.5 + 0.0 * np.exp(1.0) - 1.0
    assert float(loss.level(pred, gt).detach()) == pytest.approx(expect, rel=1e-6)
    pred2 = torch.tensor([[0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0]])  # 180 deg about x: |q_gt - q|^2 = 2
    assert float(loss.level(pred2, gt).detach()) == pytest.approx(0.5 + 2 * np.exp(1.0) - 1.0, rel=1e-6)


def test_config_validation():
    with pytest.raises(ValueError, match="divisible by 16"):
        D3LVOConfig(height=350)
    with pytest.raises(ValueError, match="mode"):
        D3LVOConfig(mode="lidar")
    assert D3LVOConfig(mode="rgb_completion", completion="ipbasic").depth_input == "ipbasic"
    assert D3LVOConfig.from_dict(D3LVOConfig.small().to_dict()) == D3LVOConfig.small()
