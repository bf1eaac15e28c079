"""The synthetic KITTI world: layout, determinism, resume, and LiDAR/camera geometric consistency."""

import hashlib
import re
from dataclasses import replace

import cv2
import numpy as np
import pytest
from conftest import shared_path

from d3lvo_deploy.errors import D3LVOInputError
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
    """Scan k, moved into frame 0 with the poses of poses.txt (velodyne -> cam0 of k -> world ->
    cam0 of 0 -> cam2), lands on frame 0's rendered depth within 1 cm (median; measured 0.8 mm); with
    the motion scaled by 1.2 the median is 3x larger or more (measured 4x, 10x: points on the road
    slide along it, so the photometric test below is the sharper check of a scaled motion)."""
    seq = KittiSequence.open(small_synth)
    gt, calib = seq.ground_truth.poses, seq.calib
    zbuf = cv2.imread(str(small_synth / "depth_2" / "000000.png"), cv2.IMREAD_UNCHANGED) / 256.0
    h, w = zbuf.shape
    K = calib.K2

    def median_error(k: int, scale: float) -> float:
        A = np.linalg.inv(gt[0]) @ gt[k]  # frame k's cam0 in frame 0's
        A[:3, 3] *= scale
        X = np.c_[seq.scan(k)[:, :3].astype(np.float64), np.ones(len(seq.scan(k)))]
        Xc = (calib.T_cam2_cam0 @ A @ calib.Tr @ X.T).T
        z = Xc[:, 2]
        front = z > 1.0
        u, v, z = K[0, 0] * Xc[front, 0] / z[front] + K[0, 2], K[1, 1] * Xc[front, 1] / z[front] + K[1, 2], z[front]
        inside = (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1) & (z < 40)
        d, ok = _zbuffer_at(zbuf, u[inside], v[inside])
        assert ok.sum() > 3000
        return float(np.median(np.abs(d[ok] - z[inside][ok])))

    for k in (2, 5):
        true, scaled = median_error(k, 1.0), median_error(k, 1.2)
        print(k, true, scaled)
        assert true < 0.01 and scaled > 3 * true, (k, true, scaled)


def test_frames_warped_by_the_written_poses_match(small_synth):
    """Frame 0's pixels, back-projected with its z-buffer and moved by the GT motion of poses.txt
    into frame k, find the same colour there; with the motion scaled by 0.8 or 1.2 they do not.
    (A depth-only check misses a scaled motion: a point slid along the road or a facade stays on it.)"""
    seq = KittiSequence.open(small_synth)
    gt = seq.ground_truth.poses
    zbuf = cv2.imread(str(small_synth / "depth_2" / "000000.png"), cv2.IMREAD_UNCHANGED) / 256.0
    img0 = seq.image(0).astype(np.float32)
    K = seq.calib.K2
    h, w = zbuf.shape
    grey = img0.mean(-1)
    grad = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
    textured = grad > np.percentile(grad, 80)  # where a wrong warp shows
    v, u = np.nonzero((zbuf > 0) & (zbuf < 40) & textured)
    z = zbuf[v, u]
    X0 = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z, np.ones_like(z)])

    def photometric_error(k, scale):
        A = seq.calib.T_cam2_cam0 @ relative(gt[0], gt[k]) @ seq.calib.T_cam0_cam2  # frame k in frame 0, cam2
        A[:3, 3] *= scale
        Xk = np.linalg.inv(A) @ X0
        uk, vk = K[0, 0] * Xk[0] / Xk[2] + K[0, 2], K[1, 1] * Xk[1] / Xk[2] + K[1, 2]
        ok = (Xk[2] > 1) & (uk >= 0) & (uk <= w - 1) & (vk >= 0) & (vk <= h - 1)
        n = int(ok.sum()) // 256 * 256  # remap's maps are images: fold the points into rows of 256
        mx, my = (c[ok][:n].astype(np.float32).reshape(-1, 256) for c in (uk, vk))
        got = cv2.remap(seq.image(k).astype(np.float32), mx, my, cv2.INTER_LINEAR).reshape(-1, 3)
        ref = img0[v[ok][:n], u[ok][:n]]
        return float(np.median(np.abs(got - ref).mean(-1)))

    for k in (2, 5):
        true, short, long = (photometric_error(k, s) for s in (1.0, 0.8, 1.2))
        print(k, true, short, long)
        assert true < 0.5 * min(short, long), (k, true, short, long)


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
    with pytest.raises(D3LVOInputError, match=r"other settings \(seed 1 there, 2 asked\).*--overwrite"):
        generate(tmp_path / "s", SynthConfig(frames=2, seed=2, width=320, height=96))
    with pytest.raises(D3LVOInputError, match=r"other settings \(traffic unset there, 2.0 asked\)"):  # a static render
        generate(tmp_path / "s", SynthConfig(frames=2, seed=1, width=320, height=96, traffic=2.0))
    generate(tmp_path / "s", SynthConfig(frames=2, seed=2, width=320, height=96), resume=False)  # --overwrite


def test_a_traffic_render_says_whether_it_kept_vehicles_that_run_into_the_camera(tmp_path):
    """With traffic, synth.json names `ego_collisions` either way (a static one does not); a file
    that does not name it kept every vehicle, so it reads as true: resuming it with the default
    is refused by that key, with `ego_collisions` it resumes."""
    import json

    from d3lvo_deploy.synth.generator import rendered_settings

    cfg = SynthConfig(frames=2, seed=1, width=320, height=96, traffic=2.0)
    out = generate(tmp_path / "t", cfg)
    assert json.loads((out / "synth.json").read_text())["ego_collisions"] is False
    assert "ego_collisions" not in SynthConfig(frames=2, ego_collisions=True).meta()
    written = json.loads((out / "synth.json").read_text())
    del written["ego_collisions"]
    (out / "synth.json").write_text(json.dumps(written))
    assert rendered_settings(out)["ego_collisions"] is True
    with pytest.raises(D3LVOInputError, match=r"other settings \(ego_collisions True there, False asked\)"):
        generate(out, cfg)
    generate(out, replace(cfg, ego_collisions=True))


def test_motion_replays_real_gt(tmp_path):
    gt_file = shared_path("kitti_gt_poses", "05.txt")
    out = generate(tmp_path / "r", SynthConfig(frames=4, seed=0, width=320, height=96,
                                                motion_from=str(gt_file), motion_start=100))
    gt = read_poses(gt_file).poses[100:104]
    np.testing.assert_allclose(read_poses(out / "poses.txt").poses, relative(gt[0], gt), atol=1e-8)


def test_motion_in_millimetres_is_refused_before_any_render(tmp_path):
    """A trajectory in millimetres (steps of ~1,000 "m" a frame) would build a world kilometres
    long: one error naming the file and the step, nothing written."""
    from d3lvo_deploy.poses import write_poses
    from d3lvo_deploy.synth.motion import MAX_STEP_M

    poses = np.tile(np.eye(4), (6, 1, 1))
    poses[:, 2, 3] = 1000.0 * np.arange(6)  # 1 m a frame, in millimetres
    write_poses(tmp_path / "mm.txt", poses)
    words = r"mm.txt: moves 1000.0 m between frames 0 and 1 \(lines 1 and 2\): .* more than 10 m"
    with pytest.raises(D3LVOInputError, match=words):
        generate(tmp_path / "out", SynthConfig(frames=4, seed=0, width=320, height=96,
                                               motion_from=str(tmp_path / "mm.txt")))
    assert not (tmp_path / "out").exists()
    poses[:, 2, 3] = MAX_STEP_M * np.arange(6)  # at the bound: a fast drive, accepted
    write_poses(tmp_path / "fast.txt", poses)
    from d3lvo_deploy.synth.motion import replay_gt

    assert replay_gt(tmp_path / "fast.txt", 4).shape == (4, 4, 4)


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


@pytest.mark.parametrize("cfg, words", [
    (dict(seed=-1), "--seed must be 0 or more, not -1"),
    (dict(traffic=float("nan")), "--traffic must be 0 or more vehicles per 100 m, not nan"),
    (dict(traffic=float("inf")), "--traffic must be 0 or more vehicles per 100 m, not inf"),
    (dict(motion_start=50), "--motion-start is the first frame of --motion-from's trajectory"),
    (dict(width=40000, height=40000), "--size 40000x40000 is too large: at most 4096 a side"),
    (dict(frames=99_999_999_999), "--frames 99999999999 is too many: at most 100000"),
])
def test_settings_that_cannot_render_are_refused_before_any_folder(tmp_path, cfg, words):
    from d3lvo_deploy.errors import D3LVOInputError

    with pytest.raises(D3LVOInputError, match=re.escape(words)):
        generate(tmp_path / "s", SynthConfig(**{"frames": 2, "width": 320, "height": 96, **cfg}))
    assert not (tmp_path / "s").exists()


def test_overwrite_with_fewer_frames_leaves_none_of_the_old_ones(tmp_path):
    from d3lvo_deploy.sequence import KittiSequence

    generate(tmp_path / "s", SynthConfig(frames=4, seed=1, width=320, height=96, traffic=3.0))
    generate(tmp_path / "s", SynthConfig(frames=3, seed=1, width=320, height=96, traffic=3.0), resume=False)
    assert sorted(p.name for p in (tmp_path / "s" / "motion_2").iterdir()) == ["000000.png", "000001.png", "000002.png"]
    # without traffic: the earlier drive's flow, masks and shadows go, which training would read
    generate(tmp_path / "s", SynthConfig(frames=2, seed=1, width=320, height=96), resume=False)
    seq = KittiSequence.open(tmp_path / "s")  # 2 images, 2 scans, 2 times, 2 poses
    assert len(seq) == 2 and len(seq.ground_truth) == 2
    assert not any((tmp_path / "s" / d).exists() for d in ("motion_2", "flow_2", "shadow_2"))
    # a folder of frames this command did not render (a real sequence?) is refused, its files kept
    (tmp_path / "k" / "image_2").mkdir(parents=True)
    (tmp_path / "k" / "image_2" / "000009.png").write_bytes(b"real data")
    for resume in (True, False):
        with pytest.raises(D3LVOInputError, match="holds frames that d3lvo synth did not render"):
            generate(tmp_path / "k", SynthConfig(frames=2, seed=1, width=320, height=96), resume=resume)
    assert (tmp_path / "k" / "image_2" / "000009.png").read_bytes() == b"real data"
    assert sorted(p.name for p in (tmp_path / "k").iterdir()) == ["image_2"]


def test_folders_synth_cannot_own_are_refused_and_the_user_files_kept(tmp_path, monkeypatch):
    """An empty --out (the working directory, holding the user's files), a folder with a trajectory or calibration but no
    synth.json (someone's sequence), a synth.json that is damaged or a folder: one error each,
    before anything is written; --overwrite renders a damaged one's folder again."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.md").write_text("mine")
    cfg = SynthConfig(frames=2, seed=1, width=320, height=96)
    with pytest.raises(D3LVOInputError, match="--out is the working directory, which holds other files"):
        generate("", cfg)
    assert [p.name for p in tmp_path.iterdir()] == ["notes.md"]
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(D3LVOInputError, match=r"holds poses.txt that d3lvo synth did not write"):
        generate(theirs, cfg)
    assert sorted(p.name for p in theirs.iterdir()) == ["poses.txt"]
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    for text in ("{bad", "[1, 2]", "\xff"):
        (damaged / "synth.json").write_text(text)
        with pytest.raises(D3LVOInputError, match=r"synth.json: is not the settings file d3lvo synth writes"):
            generate(damaged, cfg)
    generate(damaged, cfg, resume=False)  # --overwrite
    assert len(KittiSequence.open(damaged)) == 2
    (tmp_path / "dir" / "synth.json").mkdir(parents=True)
    with pytest.raises(D3LVOInputError, match=r"synth.json: is not a file"):
        generate(tmp_path / "dir", cfg, resume=False)
