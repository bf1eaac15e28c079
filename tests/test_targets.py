"""Training targets: true flow through the augmentations, held-out LiDAR returns for completion,
flow targets centred on the encoder's cells, moving shadows in the confidence's target, and the
AUROC of the confidence against motion masks."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from d3lvo_deploy.metrics import auroc
from models.config import D3LVOConfig
from models.data import AugmentConfig, PairDataset
from models.train import level_flow_target, motion_loss

ROOT = Path(__file__).resolve().parents[1]
NO_AUG = dict(flip=0.0, brightness=0.0, rotation_deg=0.0, cold_start=0.0, held_out_returns=0.0)


def test_auroc_by_hand():
    """Scores 0.1, 0.4, 0.35, 0.8 with the last two positive: of the 4 (positive, negative) pairs
    3 are ranked right (0.35 < 0.4 is the miss): 0.75. Ties count one half; one class: None."""
    assert auroc(np.array([0.1, 0.4, 0.35, 0.8]), np.array([0, 0, 1, 1])) == 0.75
    assert auroc(np.array([1.0, 1.0, 2.0]), np.array([1, 0, 1])) == 0.75
    assert auroc(np.ones(5), np.array([1, 0, 1, 0, 0])) == 0.5
    assert auroc(np.arange(3.0), np.zeros(3)) is None


def test_flow_target_sits_on_the_encoders_cells():
    """A horizontal flow equal to the pixel column u: at a level of stride s the encoder's cell j
    is pixel s*j, so its target is s*j / s = j cells (a plain s-wide pooling would give
    j + (s-1)/(2s), half a cell off at large s)."""
    h, w = 32, 64
    u = torch.arange(w, dtype=torch.float64).expand(h, w)
    flow = torch.stack([u, torch.zeros_like(u)])[None]
    for s in (2, 4, 8):
        g, m = level_flow_target(flow, torch.ones(1, 1, h, w, dtype=torch.float64), (h // s, w // s))
        j = torch.arange(w // s, dtype=torch.float64)
        assert m.all()
        torch.testing.assert_close(g[0, 0, h // s // 2, 1:], j[1:], rtol=0, atol=1e-12)  # column 0 is the border


def _cfg(width: int, height: int) -> D3LVOConfig:
    return D3LVOConfig.small(height=height, width=width)


@pytest.fixture(scope="module")
def traffic_pairs(traffic_clip):
    cfg = _cfg(416, 128)
    plain = PairDataset([traffic_clip], cfg, augment=AugmentConfig(**NO_AUG))
    return cfg, plain


def test_true_flow_target_is_the_written_flow(traffic_clip, traffic_pairs):
    """Without augmentation the target is flow_2 as written (this clip is rendered at the network
    size, so the view is the identity), and the moving mask is motion_2."""
    cfg, plain = traffic_pairs
    s = plain[2]  # pair (2, 3): the flow written for frame 2
    png = cv2.imread(str(traffic_clip / "flow_2" / "000002.png"), cv2.IMREAD_UNCHANGED)
    written = (np.dstack([png[..., 2], png[..., 1]]).astype(np.float64) - 32768.0) / 64.0
    valid = png[..., 0] > 0
    got = s["flow"].numpy().transpose(1, 2, 0)
    assert np.abs(got[valid] - written[valid]).max() < 1e-4
    assert (s["flow_valid"][0].numpy() > 0).tolist() == valid.tolist()
    mask = cv2.imread(str(traffic_clip / "motion_2" / "000002.png"), cv2.IMREAD_UNCHANGED) > 0
    assert mask.sum() > 100 and (s["moving"][0].numpy() > 0.5).tolist() == mask.tolist()
    shade = cv2.imread(str(traffic_clip / "shadow_2" / "000002.png"), cv2.IMREAD_UNCHANGED) > 0
    assert shade.sum() > 20 and (s["shadow"][0].numpy() > 0.5).tolist() == shade.tolist()


def test_true_flow_follows_flip_and_rotation(traffic_pairs):
    """Mirrored, the target is the mirror image with u negated; rotated by 2 deg, warping frame t
    back with it matches frame t-1 on the vehicles as well as without the rotation."""
    cfg, plain = traffic_pairs
    ref = plain[2]
    flipped = PairDataset([plain.loaders[0].seq.root], cfg,
                          augment=AugmentConfig(**{**NO_AUG, "flip": 1.0}))[2]
    f_ref, f_flip = ref["flow"].numpy(), flipped["flow"].numpy()[:, :, ::-1]
    ok = ref["flow_valid"][0].numpy() > 0
    assert np.abs(f_flip[0][ok] + f_ref[0][ok]).max() < 1e-4 and np.abs(f_flip[1][ok] - f_ref[1][ok]).max() < 1e-4
    for mask in ("moving", "shadow"):  # the masks mirror with the images
        assert ref[mask].sum() > 0 and torch.equal(flipped[mask].flip(-1), ref[mask])

    def warp_error(s) -> float:
        img1, img2 = s["rgb1"].numpy().transpose(1, 2, 0), s["rgb2"].numpy().transpose(1, 2, 0)
        h, w = img1.shape[:2]
        v, u = np.mgrid[0:h, 0:w].astype(np.float32)
        f = s["flow"].numpy()
        warped = cv2.remap(img2, u + f[0], v + f[1], cv2.INTER_LINEAR)
        sel = (s["flow_valid"][0].numpy() > 0) & (s["moving"][0].numpy() > 0.5)
        return float(np.percentile(np.abs(warped - img1).mean(2)[sel], 75))

    rotated = PairDataset([plain.loaders[0].seq.root], cfg, augment=AugmentConfig(**{**NO_AUG, "rotation_deg": 2.0}))[2]
    e_ref, e_rot = warp_error(ref), warp_error(rotated)
    print(f"75th-percentile warp error on vehicles: {e_ref:.4f} plain, {e_rot:.4f} rotated")
    assert e_rot < 1.5 * e_ref + 0.01


def test_motion_target_counts_moving_shadows_only_when_asked():
    """Two cells at stride 1, logit +2 on both: a cell whose target is 1 costs log(1 + e^-2), one
    whose target is 0 log(1 + e^2).
    A pixel in a moving shadow is target 0 without `shadows`, 1 with; an unknown shadow mask
    (-1, real KITTI) leaves the vehicles' target as it is."""
    out = {"moving_logits": torch.full((1, 1, 1, 2), 2.0)}
    batch = {"moving": torch.tensor([[[[1.0, 0.0]]]]), "shadow": torch.tensor([[[[0.0, 1.0]]]])}
    lo, hi = float(np.log1p(np.exp(-2.0))), float(np.log1p(np.exp(2.0)))
    assert abs(float(motion_loss(out, batch, "cpu")) - (lo + hi) / 2) < 1e-6
    assert abs(float(motion_loss(out, batch, "cpu", shadows=True)) - lo) < 1e-6
    unknown = {**batch, "shadow": torch.full((1, 1, 1, 2), -1.0)}
    assert abs(float(motion_loss(out, unknown, "cpu", shadows=True)) - (lo + hi) / 2) < 1e-6


def test_completion_target_is_held_out_of_the_input():
    """Without depth_2/ (real-KITTI layout) a fifth of the returns is the completion target and
    not in the depth input: the two share almost no pixel, and the target has about a fifth of
    the pixels of the full scan."""
    seq = ROOT / "tests" / "data" / "tiny_seq"
    cfg = _cfg(608, 176)
    s = PairDataset([seq], cfg, augment=AugmentConfig(**{**NO_AUG, "held_out_returns": 0.2}))[0]
    full = PairDataset([seq], cfg, augment=AugmentConfig(**NO_AUG))[0]
    inp, tgt, all_px = s["depth1"][0] > 0, s["gt_depth1"][0] > 0, full["gt_depth1"][0] > 0
    both = int((inp & tgt).sum())
    print(f"input {int(inp.sum())} px, target {int(tgt.sum())} px, shared {both}, full {int(all_px.sum())}")
    assert 0.12 < tgt.sum() / all_px.sum() < 0.3
    assert both < 0.1 * tgt.sum()
    # the full scan is still used for the rigid flow: it covers as many pixels as without holding out
    assert torch.equal(s["flow_valid"], full["flow_valid"])


def test_true_flow_agrees_with_rigid_flow_on_static_pixels_through_a_resize(tmp_path):
    """A 620x188 drive seen by a 608x176 network (crop 620x179, resize 0.98): on pixels off the
    vehicles the true-flow target equals the rigid flow of the GT motion through the z-buffer, to
    well under a pixel (resampling target positions instead of displacements would put it about
    half a pixel off in u and v)."""
    pytest.importorskip("embreex")
    from d3lvo_deploy.synth.generator import SynthConfig, generate
    from models.data import rigid_flow

    seq = generate(tmp_path / "seq", SynthConfig(frames=3, seed=8, width=620, height=188, traffic=6.0))
    data = PairDataset([seq], _cfg(608, 176), augment=AugmentConfig(**NO_AUG))
    s = data[0]
    K = data.loaders[0].K
    rigid, ok = rigid_flow(s["gt_depth1"][0].numpy(), K, s["matrix"].numpy().astype(np.float64))
    sel = (ok[0] > 0) & (s["flow_valid"][0].numpy() > 0) & (s["moving"][0].numpy() < 0.5)
    d = s["flow"].numpy()[:, sel] - rigid[:, sel]
    print(f"median (u, v) difference {np.median(d, axis=1).round(3)} px over {sel.sum()} pixels")
    assert sel.sum() > 10000
    assert np.abs(np.median(d, axis=1)).max() < 0.1 and np.percentile(np.linalg.norm(d, axis=0), 75) < 0.3
