"""Calibration parsing (odometry, object-benchmark and 4x4 variants) and the cam0/cam2 convention."""

import numpy as np
import pytest
from conftest import shared_path

from d3lvo_deploy.calib import parse_calib
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
