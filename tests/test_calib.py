"""Calibration parsing (odometry, object-benchmark and 4x4 variants) and the cam0/cam2 convention."""

import re
import warnings

import numpy as np
import pytest
from conftest import ROOT, SHARED, shared_path

from d3lvo_deploy.calib import Calib, check_fit, parse_calib
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.geometry import axis_angle_to_rot, change_frame, make_se3, relatives


def test_real_odometry_calib_and_baseline():
    c = parse_calib(shared_path("kitti_raw_snippet", "sequences", "r0926", "calib.txt"))
    assert c.P2[0, 0] == pytest.approx(721.5377)
    # hand: b = inv(K2) @ P2[:, 3]; bz = 0.002745884, bx = (44.85728 - 609.5593 bz) / 721.5377
    bz = 0.002745884
    bx = (44.85728 - 609.5593 * bz) / 721.5377
    np.testing.assert_allclose(c.T_cam2_cam0[:3, 3], [bx, (0.2163791 - 172.854 * bz) / 721.5377, bz], rtol=1e-9)
    assert 0.05 < bx < 0.07  # image_2 is ~6 cm from cam0 on the KITTI rig
    np.testing.assert_allclose(c.Tr[:3, :3] @ c.Tr[:3, :3].T, np.eye(3), atol=1e-6)


def test_object_benchmark_calib_applies_r0_rect():
    path = shared_path("kitti_object_frames", "calib", "000000.txt")
    c = parse_calib(path)
    vals = {l.split(":")[0]: np.array(l.split(":")[1].split(), float) for l in path.read_text().splitlines() if ":" in l}
    R0 = np.eye(4)
    R0[:3, :3] = vals["R0_rect"].reshape(3, 3)
    V = np.vstack([vals["Tr_velo_to_cam"].reshape(3, 4), [0, 0, 0, 1]])
    np.testing.assert_allclose(c.Tr, R0 @ V)


def test_4x4_and_missing_entries(tmp_path):
    P = "P2: 700 0 600 45 0 700 180 0 0 0 1 0.003\n"
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, -0.3]
    f = tmp_path / "calib.txt"
    f.write_text(P + "Tr: " + " ".join(map(str, T.reshape(-1))) + "\n")
    np.testing.assert_allclose(parse_calib(f).Tr, T)
    f.write_text(P)
    with pytest.raises(D3LVOInputError, match="calib.txt.*Tr"):
        parse_calib(f)
    f.write_text("Tr: " + " ".join(map(str, T.reshape(-1))) + "\n")
    with pytest.raises(D3LVOInputError, match="no P2"):
        parse_calib(f)
    f.write_text(P + "Tr: 1 2 3\n")
    with pytest.raises(D3LVOInputError, match="3 numbers"):
        parse_calib(f)


def test_written_calib_round_trips(tmp_path):
    from d3lvo_deploy.synth.generator import kitti_calib

    c = kitti_calib()
    f = tmp_path / "calib.txt"
    f.write_text(c.to_text())
    back = parse_calib(f)
    np.testing.assert_allclose(back.P2, c.P2)
    np.testing.assert_allclose(back.Tr, c.Tr)


def test_cam2_motion_maps_back_to_cam0_ground_truth():
    """What the network estimates (cam2 motion) converted with T_cam0_cam2 equals the cam0 GT motion."""
    from d3lvo_deploy.synth.generator import kitti_calib

    c = kitti_calib()
    poses0 = np.stack([make_se3(axis_angle_to_rot([0.01 * i, 0.2 * i, 0.0]), [0.3 * i, 0.0, 2.0 * i]) for i in range(6)])
    poses2 = poses0 @ c.T_cam0_cam2  # where image_2 was at each frame
    rel2 = relatives(poses2)
    rel0 = np.stack([change_frame(A, c.T_cam0_cam2) for A in rel2])
    np.testing.assert_allclose(rel0, relatives(poses0), atol=1e-12)
    # and the difference is real: with a yaw, cam2's own motion has a different translation
    assert np.abs(rel2[:, :3, 3] - relatives(poses0)[:, :3, 3]).max() > 1e-3


@pytest.mark.parametrize("text, words", [
    ("K: 1 2 3 4 5 6 7 8\n", "K has 8 numbers, expected 9 (3x3)"),
    ("K: 0 0 300 0 700 90 0 0 1\n", "K's focal lengths must be positive (fx 0, fy 700)"),
    ("P2: 700 0 300 0 0 -700 90 0 0 0 1 0\n", "P2's focal lengths must be positive (fx 700, fy -700)"),
])
def test_a_camera_matrix_that_cannot_project_is_named(tmp_path, text, words):
    f = tmp_path / "calib.txt"
    f.write_text(text + "T_cam_lidar: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(D3LVOInputError, match=re.escape(words)):
        parse_calib(f)


def _fit_warnings(calib, image, scan):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_fit(calib, image.shape[1], image.shape[0], scan, "rec", "000000")
    return [str(w.message) for w in caught]


def test_a_calibration_that_fits_raises_nothing(small_synth):
    from d3lvo_deploy.sequence import KittiSequence

    seqs = [KittiSequence.open(small_synth), KittiSequence.open(ROOT / "tests" / "data" / "tiny_seq")]
    real = SHARED / "kitti_raw_snippet" / "sequences" / "r0926"
    seqs += [KittiSequence.open(real)] if real.is_dir() else []
    for seq in seqs:
        assert _fit_warnings(seq.calib, seq.image(0), seq.scan(0)) == [], seq.root


def test_a_calibration_for_another_image_or_rig_is_caught(small_synth):
    """The synthetic drive's own calibration (principal point near 304, 87 for 620x188 images) and
    360-degree scan: images resized to half their size keep the principal point inside, at 98 % and
    92 % (a warning), and only returns on the top left of the view land in them (under 2 %, a
    warning); a 150x40 image leaves it outside (an error). A LiDAR extrinsic that looks up
    (identity: the LiDAR's z, up, as the camera's forward axis) puts no return of a scan ahead of
    and below the sensor in the image (an error)."""
    from d3lvo_deploy.sequence import KittiSequence

    seq = KittiSequence.open(small_synth)
    c, scan = seq.calib, seq.scan(0)
    pp = f"({c.P2[0, 2]:.1f}, {c.P2[1, 2]:.1f})"
    assert pp.startswith("(304.") and (", 86." in pp or ", 87." in pp)
    half = _fit_warnings(c, np.zeros((94, 310, 3), np.uint8), scan)
    assert len(half) == 2 and f"{pp} is far from the centre of frame 000000's 310x94 image" in half[0], half
    assert "LiDAR returns of frame 000000" in half[1] and "land in its 310x94 image" in half[1], half
    with pytest.raises(D3LVOInputError, match=re.escape(f"{pp} lies outside frame 000000's 150x40 image")):
        check_fit(c, 150, 40, scan, "rec", "000000")
    rng = np.random.default_rng(0)
    # 5,000 returns 5-40 m ahead of the LiDAR (x forward), up to 15 m to either side, below it
    ahead = np.stack([rng.uniform(5, 40, 5000), rng.uniform(-15, 15, 5000), rng.uniform(-1.7, -0.2, 5000),
                      np.ones(5000)], 1).astype(np.float32)
    assert _fit_warnings(c, seq.image(0), ahead) == []
    up = Calib(P2=c.P2, Tr=np.eye(4))
    with pytest.raises(D3LVOInputError, match="none of the 5000 LiDAR returns of frame 000000 lands in its 620x188"):
        check_fit(up, 620, 188, ahead, "rec", "000000")
    # an empty or sparse scan is not judged (its own warning says it is empty)
    assert _fit_warnings(up, seq.image(0), ahead[:999]) == []
