"""The synthetic KITTI world: layout, determinism, resume, and LiDAR/camera geometric consistency."""

import hashlib

import cv2
import numpy as np
import pytest
from conftest import shared_path

from d3lvo_deploy.geometry import relative
from d3lvo_deploy.poses import read_poses
from d3lvo_deploy.sequence import KittiSequence
from d3lvo_deploy.synth.generator import SynthConfig, generate


def _digest(folder):
    h = hashlib.sha256()
    for f in sorted(p for p in folder.rglob("*") if p.is_file() and p.name != "synth.json"):
        h.update(f.relative_to(folder).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def test_layout_is_a_readable_kitti_sequence(small_synth):
    seq = KittiSequence.open(small_synth)
    assert len(seq) == 6
    img = seq.image(0)
    assert img.shape == (188, 620, 3) and img.dtype == np.uint8
    assert img.std() > 20  # textured, not a flat render
    gt = seq.ground_truth
    np.testing.assert_allclose(gt.poses[0], np.eye(4), atol=1e-9)
    assert len(gt) == 6
    np.testing.assert_allclose(seq.times, np.arange(6) * 0.1, atol=1e-6)


def test_lidar_matches_an_hdl64(small_synth):
    seq = KittiSequence.open(small_synth)
    pts = seq.scan(0)
    r = np.linalg.norm(pts[:, :3], axis=1)
    elev = np.degrees(np.arcsin(pts[:, 2] / r))
    assert r.max() <= 120.0 and r.min() >= 2.5
    assert elev.min() > -24.9 and elev.max() < 2.1
    assert len(np.unique(np.round(elev, 1))) > 50  # 64 rings (minus rings that see only sky)
    assert np.all((pts[:, 3] >= 0) & (pts[:, 3] <= 1))


def _zbuffer_at(zbuf, u, v):
    """Depth at sub-pixel (u, v) inside the image: inverse depth (exactly linear in the image on a
    plane) interpolated between the 4 pixel centres; valid where all 4 have depth."""
    inv = np.where(zbuf > 0, 1.0 / np.maximum(zbuf, 1e-6), 0.0)
    x0, y0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fx, fy = u - x0, v - y0
    q = [inv[y0, x0], inv[y0, x0 + 1], inv[y0 + 1, x0], inv[y0 + 1, x0 + 1]]
    ok = np.all([a > 0 for a in q], axis=0)
    inv_i = (q[0] * (1 - fx) + q[1] * fx) * (1 - fy) + (q[2] * (1 - fx) + q[3] * fx) * fy
    return 1.0 / np.where(ok, inv_i, 1.0), ok


def test_projected_lidar_lands_on_rendered_geometry(small_synth):
    """LiDAR points projected with the written calib hit the renderer's z-buffer to the centimetre."""
    seq = KittiSequence.open(small_synth)
    for i in (0, 5):
        zbuf = cv2.imread(str(small_synth / "depth_2" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED) / 256.0
        P = seq.calib.P_velo_to_image2
        xyz = seq.scan(i)[:, :3].astype(np.float64)
        uvw = xyz @ P[:, :3].T + P[:, 3]
        z = uvw[:, 2]
        front = z > 1.0
        u, v, z = uvw[front, 0] / z[front], uvw[front, 1] / z[front], z[front]
        h, w = zbuf.shape
        inside = (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1)
        u, v, z = u[inside], v[inside], z[inside]
        d, ok = _zbuffer_at(zbuf, u, v)
        ok &= z < 40
        err = np.abs(d[ok] - z[ok])
        assert ok.sum() > 5000
        assert np.median(err) < 0.005  # z-buffer PNGs quantise to 4 mm
        assert np.percentile(err, 90) < 0.02  # the rest: points on depth edges between pixel centres


def test_scans_moved_by_the_written_poses_land_on_frame_0(small_synth):
    """Scan k, moved into frame 0 with the GT poses of poses.txt, hits frame 0's z-buffer: the
    camera moved exactly as written (a renderer that moved it 1.2x the written motion fails)."""
    seq = KittiSequence.open(small_synth)
    gt = seq.ground_truth.poses
    zbuf = cv2.imread(str(small_synth / "depth_2" / "000000.png"), cv2.IMREAD_UNCHANGED) / 256.0
    h, w = zbuf.shape
    K = seq.calib.K2
    for k in (2, 5):
        xyz = np.c_[seq.scan(k)[:, :3].astype(np.float64), np.ones(len(seq.scan(k)))]
        # velodyne of frame k -> cam0 of frame k -> cam0 of frame 0 -> cam2 of frame 0
        X = (seq.calib.T_cam2_cam0 @ relative(gt[0], gt[k]) @ seq.calib.Tr @ xyz.T)[:3].T
        X = X[(X[:, 2] > 1.0) & (X[:, 2] < 40)]
        uv = X @ K.T
        u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
        inside = (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1)
        d, ok = _zbuffer_at(zbuf, u[inside], v[inside])
        err = np.abs(X[inside, 2] - d)[ok]
        assert len(err) > 3000
        # visible points agree to the centimetre; occluded ones (seen from frame k only) lie behind
        assert np.median(err) < 0.01, (k, np.median(err))


def test_same_seed_same_bytes_and_resume(tmp_path):
    cfg = SynthConfig(frames=3, seed=11, width=320, height=96)
    a = generate(tmp_path / "a", cfg)
    b = generate(tmp_path / "b", cfg)
    assert _digest(a) == _digest(b)
    (b / "image_2" / "000001.png").unlink()
    (b / "velodyne" / "000002.bin").unlink()
    generate(b, cfg)  # resumes: only the missing frames are rendered again
    assert _digest(a) == _digest(b)
    c = generate(tmp_path / "c", SynthConfig(frames=3, seed=12, width=320, height=96))
    assert _digest(a) != _digest(c)


def test_other_settings_in_the_same_folder_are_refused(tmp_path):
    from d3lvo_deploy.errors import D3LVOInputError

    generate(tmp_path / "s", SynthConfig(frames=2, seed=1, width=320, height=96))
    with pytest.raises(D3LVOInputError, match="other settings"):
        generate(tmp_path / "s", SynthConfig(frames=2, seed=2, width=320, height=96))


def test_motion_replays_real_gt(tmp_path):
    gt_file = shared_path("kitti_gt_poses", "05.txt")
    out = generate(tmp_path / "r", SynthConfig(frames=4, seed=0, width=320, height=96,
                                                motion_from=str(gt_file), motion_start=100))
    gt = read_poses(gt_file).poses[100:104]
    np.testing.assert_allclose(read_poses(out / "poses.txt").poses, relative(gt[0], gt), atol=1e-8)


def test_synthetic_drive_is_plausible():
    from d3lvo_deploy.synth.motion import synthetic_drive

    poses = synthetic_drive(600, seed=1)
    speed = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) / 0.1
    assert speed.max() < 14.0 and speed.mean() > 3.0
    assert (speed < 0.05).any()  # this seed stops at least once
    acc = np.diff(speed) / 0.1
    assert np.abs(acc).max() < 3.5  # rate-limited like a car
    # camera stays level: the y axis keeps pointing (nearly) down
    assert np.all(poses[:, 1, 1] > 0.99)
