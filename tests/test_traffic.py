"""Traffic and sensor effects in the synthetic world: movers agree between LiDAR and camera, the
written flow is the true one, and the camera effects are the ones stated."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from d3lvo_deploy.projection import project_points
from d3lvo_deploy.sequence import KittiSequence

pytest.importorskip("embreex")

from d3lvo_deploy.synth.generator import (SynthConfig, decode_kitti_flow, encode_kitti_flow, generate,  # noqa: E402
                                          make_poses, make_scene)
from d3lvo_deploy.synth.sensors import Exposure, LidarConfig, cam2_pose, render_camera, scan_lidar, velo_pose  # noqa: E402
from d3lvo_deploy.synth.raycast import RayCaster  # noqa: E402
from d3lvo_deploy.synth.traffic import KINDS, Vehicle, plan_traffic, shadow_change  # noqa: E402
from d3lvo_deploy.synth.world import Mesh, add_box  # noqa: E402
from d3lvo_deploy.synth.world import build_path  # noqa: E402

SIZE = (416, 128)


def _mask(seq_dir: Path, i: int) -> np.ndarray:
    return cv2.imread(str(seq_dir / "motion_2" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED) > 0


def test_every_kind_of_vehicle_is_planned():
    cfg = SynthConfig(frames=60, seed=3, traffic=4.0)
    poses = make_poses(cfg)
    scene = make_scene(poses, cfg.seed)
    vehicles = plan_traffic(build_path(poses), scene.style, poses, cfg.traffic, np.random.default_rng(0))
    assert {v.kind for v in vehicles} == set(KINDS)
    assert [v.kind for v in vehicles].count("lead") == 1
    # the lead car keeps its distance to the camera: it moves exactly as the camera does along the road
    lead = next(v for v in vehicles if v.kind == "lead")
    gap = np.linalg.norm(lead.poses[:, :3, 3] - poses[:, :3, 3], axis=1)
    assert gap.max() - gap.min() < 0.5


def test_a_vehicle_that_runs_into_the_cameras_car_is_dropped():
    """`meets_ego` on hand-placed boxes around a camera at the origin, whose car (`EGO_FOOTPRINT`)
    reaches 1 m either side of it, 3.5 m behind and 1.5 m ahead. A car of 4 x 1.8 m, grown by
    0.3 m: beside it, they touch below 1 + 0.9 + 0.3 = 2.2 m between the centres (2.1 m overlaps,
    2.3 m does not); turned across the road ahead, below 1.5 + 0.9 + 0.3 = 2.7 m (2.6 / 2.8 m);
    behind, within 3.5 + 2.0 + 0.3 = 5.8 m (5.7 / 5.9 m). On seed 911's own winding path with 3
    vehicles per 100 m an oncoming car's schedule runs through the camera: the plan drops it and
    keeps the other vehicles of the seed as they are (`ego_collisions` keeps it)."""
    from d3lvo_deploy.synth.traffic import meets_ego

    mesh = Mesh()
    add_box(mesh, np.zeros(3), np.array([0.0, 0.0, 1.0]), (4.0, 1.8, 1.0), 0, (0.5, 0.5, 0.5))
    car = mesh.arrays()
    ego = np.eye(4)[None]

    def at(x: float, z: float, yaw_deg: float = 0.0) -> Vehicle:
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        T = np.eye(4)
        T[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
        T[:3, 3] = [x, 0.0, z]
        return Vehicle("overtaking", car, T[None])

    assert meets_ego(at(2.1, 0.0), ego) and not meets_ego(at(2.3, 0.0), ego)
    assert meets_ego(at(-2.1, 0.0), ego) and not meets_ego(at(-2.3, 0.0), ego)
    assert meets_ego(at(0.0, 2.6, 90.0), ego) and not meets_ego(at(0.0, 2.8, 90.0), ego)
    assert meets_ego(at(0.0, -5.7), ego) and not meets_ego(at(0.0, -5.9), ego)
    cfg = SynthConfig(frames=220, seed=911, width=620, height=188, traffic=3.0, sensor_effects=True)
    poses = make_poses(cfg)
    scene = make_scene(poses, cfg.seed)
    plan = lambda clear: plan_traffic(build_path(poses), scene.style, poses, cfg.traffic,  # noqa: E731
                                      np.random.default_rng([cfg.seed, 3]), clear_ego=clear)
    every, kept = plan(False), plan(True)
    dropped = [v for v in every if not any(np.array_equal(v.poses, k.poses) for k in kept)]
    assert [v.kind for v in dropped] == ["oncoming"] and len(kept) == len(every) - 1
    assert all(meets_ego(v, poses) for v in dropped) and not any(meets_ego(v, poses) for v in kept)


def test_static_drive_writes_no_traffic_files(small_synth):
    assert not any((small_synth / d).exists() for d in ("motion_2", "flow_2", "shadow_2"))
    assert "traffic" not in (small_synth / "synth.json").read_text()


def test_movers_scan_points_land_on_their_own_pixels(traffic_clip):
    """LiDAR returns that project onto motion-mask pixels have the depth the camera rendered there:
    both sensors saw each vehicle at the same pose (a LiDAR one frame late would be ~1 m off)."""
    seq = KittiSequence.open(traffic_clip)
    diffs, masked = [], 0
    for i in range(len(seq)):
        mask = _mask(traffic_clip, i)
        depth = cv2.imread(str(traffic_clip / "depth_2" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED) / 256.0
        c, r, z = project_points(seq.scan(i), seq.calib.P_velo_to_image2, SIZE[0], SIZE[1])
        on = mask[r, c]
        masked += int(mask.sum())
        diffs.append(np.abs(z[on] - depth[r[on], c[on]]))
    d = np.concatenate(diffs)
    print(f"{len(d)} returns on moving vehicles, {masked} masked pixels, median |z - depth| {np.median(d):.4f} m")
    assert masked > 500 and len(d) > 100
    assert np.median(d) < 0.02 and np.mean(d < 0.1) > 0.8


def test_true_flow_is_rigid_on_static_pixels_and_moves_with_the_vehicles(traffic_clip):
    """Static pixels: the flow equals the rigid flow recomputed here from depth_2, poses and P2.
    Vehicles: warping frame i+1 back with the written flow matches frame i better than the rigid
    flow does (which is what an ego-motion-only flow would predict)."""
    seq = KittiSequence.open(traffic_clip)
    K = seq.calib.K2
    T02 = seq.calib.T_cam0_cam2
    v, u = np.mgrid[0:SIZE[1], 0:SIZE[0]].astype(np.float64)
    static_err, mover_written, mover_rigid = [], [], []
    for i in range(len(seq) - 1):
        png = cv2.imread(str(traffic_clip / "flow_2" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        flow, valid = decode_kitti_flow(png)
        depth = cv2.imread(str(traffic_clip / "depth_2" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED) / 256.0
        mask = _mask(traffic_clip, i)
        # rigid flow: back-project with depth, move by the camera's motion, project
        A = np.linalg.inv(seq.ground_truth.poses[i + 1] @ T02) @ (seq.ground_truth.poses[i] @ T02)
        X = np.stack([(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth], -1)
        Y = X @ A[:3, :3].T + A[:3, 3]
        rigid = np.stack([K[0, 0] * Y[..., 0] / Y[..., 2] + K[0, 2] - u, K[1, 1] * Y[..., 1] / Y[..., 2] + K[1, 2] - v], -1)
        ok = valid & (depth > 0) & ~mask
        static_err.append(np.linalg.norm(flow[ok] - rigid[ok], axis=1))
        img0 = cv2.imread(str(traffic_clip / "image_2" / f"{i:06d}.png")).astype(np.float32)
        img1 = cv2.imread(str(traffic_clip / "image_2" / f"{i + 1:06d}.png")).astype(np.float32)
        for f, out in ((flow, mover_written), (rigid, mover_rigid)):
            warped = cv2.remap(img1, (u + f[..., 0]).astype(np.float32), (v + f[..., 1]).astype(np.float32),
                               cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            out.append(np.abs(warped - img0).mean(2)[mask & valid])
    s = np.concatenate(static_err)
    written, rigid_e = np.concatenate(mover_written), np.concatenate(mover_rigid)
    print(f"static: |flow - rigid| max {s.max():.4f} px; movers ({len(written)} px): photometric error (75th "
          f"percentile) {np.percentile(written, 75):.2f} with the written flow, {np.percentile(rigid_e, 75):.2f} with "
          f"the rigid flow")
    # the format's 1/64 px step and depth_2's 1/256 m step bound the difference on static pixels
    assert s.max() < 0.05
    # a percentile, not the mean: pixels that are occluded in frame i+1 (thin roof edges, one vehicle
    # behind another) match with no flow, and their errors swamp a mean
    assert len(written) > 500 and np.percentile(written, 75) < 0.5 * np.percentile(rigid_e, 75)


def test_moving_shadow_band_by_hand():
    """A 2 x 4 m box 1 m above a plane, the sun straight overhead, moving 1 m along z between the
    frames: the plane's shading changes exactly where one footprint covers it and the other does
    not (z in [0, 1) and (4, 5] for x in [0, 2]); a parked box, or a pixel on the mover, changes nothing."""
    mesh = Mesh()
    add_box(mesh, np.array([1.0, -1.0, 2.0]), np.array([0.0, 0.0, 1.0]), (4.0, 2.0, 1.0), 0, (0.5, 0.5, 0.5))
    step = np.eye(4)
    step[2, 3] = 1.0
    box = Vehicle("lead", mesh.arrays(), np.stack([np.eye(4), step]))
    x, z = np.meshgrid(np.arange(-0.875, 3.0, 0.25), np.arange(-0.875, 6.0, 0.25))  # cell centres, no edge on a box face
    hits = {"shadow_origin": np.stack([x.ravel(), np.full(x.size, -0.02), z.ravel()], 1), "lit": np.ones(x.size)}
    sun = np.array([0.0, -1.0, 0.0])
    still = np.zeros(x.shape, bool)
    got = shadow_change(hits, still, [box], np.array([True]), sun, 0)
    inside = (x > 0) & (x < 2)
    assert (got == (inside & (((z > 0) & (z < 1)) | ((z > 4) & (z < 5))))).all() and got.sum() == 8 * 8  # 8 columns, 4 + 4 rows
    assert not shadow_change(hits, still, [box], np.array([False]), sun, 0).any()  # parked: its shadow stays
    # a static roof 3 m up over z in [4, 6] keeps the far band dark in both frames: only z in [0, 1) changes
    roof = Mesh()
    add_box(roof, np.array([1.0, -3.0, 5.0]), np.array([0.0, 0.0, 1.0]), (2.0, 2.0, 0.2), 0, (0.5, 0.5, 0.5))
    shaded = shadow_change(hits, still, [box], np.array([True]), sun, 0, RayCaster(*_faces(roof)))
    assert (shaded == (inside & (z > 0) & (z < 1))).all()
    assert not shadow_change(hits, np.ones(x.shape, bool), [box], np.array([True]), sun, 0).any()
    assert not shadow_change({**hits, "lit": np.zeros(x.size)}, still, [box], np.array([True]), sun, 0).any()


def _faces(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    a = mesh.arrays()
    return a["vertices"], a["faces"]


def test_moving_shadows_change_the_image_where_shadow_2_says(traffic_clip):
    """Pixels shadow_2 marks, warped into the next frame by the camera's motion alone (depth_2,
    poses, P2), change their brightness far more than the other static pixels: a moving shadow
    moved over them. The check reads only the rendered images, not how shadow_2 was made."""
    seq = KittiSequence.open(traffic_clip)
    K, T02 = seq.calib.K2, seq.calib.T_cam0_cam2
    v, u = np.mgrid[0:SIZE[1], 0:SIZE[0]].astype(np.float64)
    marked, rest = [], []
    for i in range(len(seq) - 1):
        shade = cv2.imread(str(traffic_clip / "shadow_2" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED) > 0
        depth = cv2.imread(str(traffic_clip / "depth_2" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED) / 256.0
        A = np.linalg.inv(seq.ground_truth.poses[i + 1] @ T02) @ (seq.ground_truth.poses[i] @ T02)
        X = np.stack([(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth], -1)
        Y = X @ A[:3, :3].T + A[:3, 3]
        z = np.maximum(Y[..., 2], 1e-3)
        mu, mv = K[0, 0] * Y[..., 0] / z + K[0, 2], K[1, 1] * Y[..., 1] / z + K[1, 2]
        g0 = cv2.imread(str(traffic_clip / "image_2" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        g1 = cv2.imread(str(traffic_clip / "image_2" / f"{i + 1:06d}.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        warped = cv2.remap(g1, mu.astype(np.float32), mv.astype(np.float32), cv2.INTER_LINEAR)
        # in view in both frames, away from depth edges (where a warp by the camera alone is wrong anyway)
        ok = (depth > 0) & (Y[..., 2] > 0.5) & (mu >= 1) & (mu <= SIZE[0] - 2) & (mv >= 1) & (mv <= SIZE[1] - 2)
        ok &= cv2.erode((~_mask(traffic_clip, i)).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        ok &= np.abs(cv2.Laplacian(depth.astype(np.float32), cv2.CV_32F)) < 0.05 * np.maximum(depth, 1.0)
        change = np.abs(warped - g0)
        marked.append(change[ok & shade])
        rest.append(change[ok & ~shade])
    m, r = np.concatenate(marked), np.concatenate(rest)
    print(f"{len(m)} marked pixels: median brightness change {np.median(m):.1f}; other static pixels "
          f"({len(r)}): {np.median(r):.1f}")
    assert len(m) > 50
    assert np.median(m) > 4 * np.median(r)


def test_kitti_flow_format_by_hand():
    """64 x flow + 2^15: (1.5, -2.25) -> 32864, 32624; the valid flag rides in the third channel."""
    enc = encode_kitti_flow(np.array([[[1.5, -2.25]]]), np.array([[True]]))
    assert enc.tolist() == [[[1, 32624, 32864]]]  # BGR: valid, v, u
    flow, valid = decode_kitti_flow(enc)
    assert flow.tolist() == [[[1.5, -2.25]]] and valid.all()


def test_exposure_gain_and_vignetting_are_as_stated():
    """Gain 1.3 scales every unclipped pixel by 1.3; vignetting 0.4 darkens the corner to 0.6 of
    the centre's value (same scene, same noise draw, noise off)."""
    cfg = SynthConfig(frames=2, seed=4, width=160, height=64)
    poses = make_poses(cfg)
    scene = make_scene(poses, cfg.seed)
    from d3lvo_deploy.synth.generator import kitti_calib

    calib = kitti_calib(160, 64)
    T = cam2_pose(poses[0], calib)

    def render(e: Exposure) -> np.ndarray:
        img, _ = render_camera(scene, calib.K2, T, 160, 64, np.random.default_rng(0), noise_sigma=0.0, exposure=e)
        return img.astype(np.float64)

    base, bright = render(Exposure()), render(Exposure(gain=1.3))
    ok = (base > 20) & (bright < 250)
    assert np.abs(bright[ok] / base[ok] - 1.3).max() < 0.05
    flat_scene_ratio = render(Exposure(vignette=0.4)) / np.maximum(base, 1)
    assert abs(flat_scene_ratio[0, 0].mean() - 0.6) < 0.05 and abs(flat_scene_ratio[32, 80].mean() - 1.0) < 0.02


def test_weak_returns_drop_out_first():
    """With the dark/far dropout, far returns are lost more often than near ones."""
    cfg = SynthConfig(frames=2, seed=4, width=160, height=64)
    poses = make_poses(cfg)
    scene = make_scene(poses, cfg.seed)
    from d3lvo_deploy.synth.generator import kitti_calib

    T = velo_pose(poses[0], kitti_calib(160, 64))
    lidar = LidarConfig(noise_m=0.0, dropout=0.0)
    full = scan_lidar(scene, T, lidar, np.random.default_rng(0))
    weak = scan_lidar(scene, T, lidar, np.random.default_rng(0), weak_dropout=1.0)
    r_full, r_weak = np.linalg.norm(full[:, :3], axis=1), np.linalg.norm(weak[:, :3], axis=1)
    near = (r_weak < 15).sum() / max((r_full < 15).sum(), 1)
    far = (r_weak > 40).sum() / max((r_full > 40).sum(), 1)
    print(f"kept near {near:.2f}, far {far:.2f}")
    assert far < near - 0.1
