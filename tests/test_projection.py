"""LiDAR -> sparse depth: hand cases, a loop reference, crop/resize registration, real scans."""

import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import shared_path

from d3lvo_deploy.calib import parse_calib
from d3lvo_deploy.projection import bottom_center_view, project_points, sparse_depth
from d3lvo_deploy.sequence import read_scan

P_SIMPLE = np.array([[100.0, 0, 50, 0], [0, 100.0, 20, 0], [0, 0, 1, 0]])


def test_hand_cases():
    pts = np.array([
        [0.0, 0.0, 10.0, 0],  # centre (50, 20)
        [0.0, 0.0, 5.0, 0],  # same pixel, nearer: wins
        [0.0, 0.0, 20.0, 0],  # same pixel, farther
        [1.0, 0.5, 10.0, 0],  # u = 60, v = 25
        [0.0, 0.0, -3.0, 0],  # behind the camera
        [10.0, 0.0, 10.0, 0],  # u = 150: outside
        [0.0049, 0.0, 1.0, 0],  # u = 50.49 -> column 50
        [0.0051, 0.0, 2.0, 0],  # u = 50.255 -> column 50
    ])
    d = sparse_depth(pts, P_SIMPLE, 100, 40)
    assert d[20, 50] == 1.0
    assert d[25, 60] == 10.0
    assert np.count_nonzero(d) == 2


def _loop_reference(points, P, w, h):
    out = {}
    for x, y, z, _ in points:
        u, v, s = P @ [x, y, z, 1.0]
        if s <= 0.1:
            continue
        c, r = int(np.floor(u / s + 0.5)), int(np.floor(v / s + 0.5))
        if not (0 <= c < w and 0 <= r < h):
            continue
        if (r, c) not in out or s < out[(r, c)]:
            out[(r, c)] = s
    d = np.zeros((h, w), np.float32)
    for (r, c), s in out.items():
        d[r, c] = s
    return d


def test_matches_loop_reference_on_random_points():
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-5, 5, (3000, 2)), rng.uniform(-2, 30, 3000), np.zeros(3000)]
    np.testing.assert_array_equal(sparse_depth(pts, P_SIMPLE, 100, 40), _loop_reference(pts, P_SIMPLE, 100, 40))
    # a float32 scan (pre-filtered by a float32 depth): the same pixels, also within 1e-6 m of min_depth
    pts[:300, 2] = 0.1 + rng.choice([-1e-6, 1e-6], 300)
    pts32 = pts.astype(np.float32)
    np.testing.assert_array_equal(sparse_depth(pts32, P_SIMPLE, 100, 40), _loop_reference(pts32, P_SIMPLE, 100, 40))


def test_crop_view_registers_with_the_image():
    view = bottom_center_view(1241, 376)
    assert (view.top, view.left, view.width, view.height) == (24, 12, 1216, 352)
    P = np.array([[700.0, 0, 620, 40], [0, 700.0, 190, 0.2], [0, 0, 1, 0.003]])
    rng = np.random.default_rng(2)
    pts = np.c_[rng.uniform(-10, 10, (500, 2)), rng.uniform(3, 40, 500)]
    cf, rf, zf = project_points(pts, P, 1241, 376)
    cc, rc, zc = project_points(pts, view.project_matrix(P), 1216, 352)
    full = {(round(z, 9)): (c - 12, r - 24) for c, r, z in zip(cf, rf, zf)}
    for c, r, z in zip(cc, rc, zc):
        assert full[round(z, 9)] == (c, r)


def test_scaled_view_matches_cv2_resize():
    """A blob centred on a source pixel lands, after cv2.resize, where the view's affine maps that pixel."""
    view = bottom_center_view(1240, 376, 1216, 352, scale=0.5)
    img = np.zeros((376, 1240), np.float32)
    img[204:214, 296:306] = 1.0  # 10x10 block aligned with the 2x2 bins, centred on (300.5, 208.5)
    c, r = 300.5, 208.5
    small = view.apply_image(img)
    ys, xs = np.mgrid[: small.shape[0], : small.shape[1]]
    centroid = np.array([(xs * small).sum(), (ys * small).sum()]) / small.sum()
    expected = (view.affine @ [c, r, 1.0])[:2]
    np.testing.assert_allclose(centroid, expected, atol=1e-3)
    # and the projection matrix goes through the same affine
    P = np.array([[700.0, 0, 620, 0], [0, 700.0, 190, 0], [0, 0, 1, 0]])
    x = np.array([1.0, 0.6, 10.0, 1.0])
    full = P @ x
    scaled = view.project_matrix(P) @ x
    np.testing.assert_allclose(scaled[:2] / scaled[2], (view.affine @ (full / full[2]))[:2])


def test_real_scan_projection():
    seq = shared_path("kitti_raw_snippet", "sequences", "r0926")
    calib = parse_calib(seq / "calib.txt")
    scan = read_scan(seq / "velodyne" / "000000.bin")
    view = bottom_center_view(1242, 375)
    t0 = time.perf_counter()
    d = sparse_depth(scan, view.project_matrix(calib.P_velo_to_image2), view.width, view.height)
    elapsed = time.perf_counter() - t0
    n = np.count_nonzero(d)
    print(f"projected {len(scan)} points into {n} pixels in {elapsed * 1000:.1f} ms")
    assert 10_000 < n < 40_000  # a 64-beam scan covers ~5% of the crop
    assert d.max() < 121 and d[d > 0].min() > 1.0
    # LiDAR rows only reach the lower part of the image: the top rows stay empty
    assert np.count_nonzero(d[:40]) < 0.05 * n


def test_real_object_frame_projection():
    root = shared_path("kitti_object_frames")
    calib = parse_calib(root / "calib" / "000000.txt")
    scan = read_scan(root / "velodyne" / "000000.bin")
    img = cv2.imread(str(root / "image_2" / "000000.png"))
    h, w = img.shape[:2]
    d = sparse_depth(scan, calib.P_velo_to_image2, w, h)
    assert np.count_nonzero(d) > 10_000


def test_truncated_scan_is_refused(tmp_path):
    from d3lvo_deploy.errors import D3LVOInputError

    f = tmp_path / "000000.bin"
    np.zeros(10, np.float32)[:-1].tofile(f)
    with pytest.raises(D3LVOInputError, match="000000.bin.*truncated"):
        read_scan(f)


def test_velodyne_point_lands_where_p2_puts_it_by_hand():
    """A point 1 m right, 0.5 m down and 10 m ahead of cam0, given to the runtime as a LiDAR return
    (through Tr's inverse), must land where KITTI's P2 puts it, with P2's fourth column (image_2 is
    6.2 cm left of cam0: 44.857 / 721.54) written out by hand: u = (fx X + cx Z + 44.857) /
    (Z + 0.0027). In the network's bottom-centre 1216x352 crop of a 1242x375 image that pixel moves
    by (-13, -23). Dropping the baseline column would move it 3.2 px."""
    from d3lvo_deploy.calib import Calib
    from d3lvo_deploy.frames import FramePreprocessor
    from d3lvo_deploy.synth.generator import KITTI_P2, KITTI_TR

    calib = Calib(P2=KITTI_P2.copy(), Tr=KITTI_TR.copy())
    X, Y, Z = 1.0, 0.5, 10.0
    u = (721.5377 * X + 609.5593 * Z + 44.85728) / (Z + 0.002745884)
    v = (721.5377 * Y + 172.854 * Z + 0.2163791) / (Z + 0.002745884)
    velo = np.linalg.inv(KITTI_TR) @ np.array([X, Y, Z, 1.0])
    scan = np.array([[*velo[:3], 0.5]], np.float32)
    c, r, z = project_points(scan, calib.P_velo_to_image2, 1242, 375)
    assert (c[0], r[0]) == (int(np.floor(u + 0.5)), int(np.floor(v + 0.5)))
    assert abs(z[0] - (Z + 0.002745884)) < 1e-4
    pre = FramePreprocessor.create(calib, 1242, 375, 1216, 352, "sparse")
    d = pre.depth(scan)
    rows, cols = np.nonzero(d)
    assert (cols.tolist(), rows.tolist()) == ([int(np.floor(u + 0.5)) - 13], [int(np.floor(v + 0.5)) - 23])


def _cull_keeps_what_the_passes_keep(scan, calib, width, height):
    """`rows_in_view` at the runtime's depth (the network's nearest, 0.1 m) and at the classical
    tracker's (the points' 0.5 m) drops only rows that neither the network's sparse depth (the
    paper's 1216x352 view and the bundled model's 608x176) nor the solver's points keep."""
    from d3lvo_deploy.points import PointConfig, visible_points
    from d3lvo_deploy.projection import PROJECTION_MIN_DEPTH, network_view, rows_in_view

    P, K, T, cfg = calib.P_velo_to_image2, calib.K2, calib.T_cam2_velo, PointConfig()
    kept = rows_in_view(scan, P, width, height, min(PROJECTION_MIN_DEPTH, cfg.min_depth))
    for net in ((1216, 352), (608, 176)):
        view = network_view(width, height, *net)
        np.testing.assert_array_equal(sparse_depth(kept, view.project_matrix(P), view.width, view.height),
                                      sparse_depth(scan, view.project_matrix(P), view.width, view.height))
    np.testing.assert_array_equal(visible_points(kept, T, K, (height, width), cfg),
                                  visible_points(scan, T, K, (height, width), cfg))
    solver_only = rows_in_view(scan, P, width, height, cfg.min_depth)  # `--method direct`
    np.testing.assert_array_equal(visible_points(solver_only, T, K, (height, width), cfg),
                                  visible_points(scan, T, K, (height, width), cfg))
    return kept


def test_view_cull_keeps_returns_at_the_borders_and_the_nearest_depth():
    """Points whose image_2 pixels straddle the image's borders (40 pixels either side), at depths
    around both nearest depths (0.1 and 0.5 m) and far: the passes give the same arrays with and
    without the cull, for a 4-column and a 3-column scan; an empty scan stays empty."""
    from d3lvo_deploy.projection import rows_in_view

    calib = parse_calib(Path(__file__).parent / "data" / "tiny_seq" / "calib.txt")
    K, T = calib.K2, calib.T_cam2_velo
    rng = np.random.default_rng(3)
    n, w, h = 40000, 1242, 375
    uv = np.c_[rng.uniform(-40, w + 40, n), rng.uniform(-40, h + 40, n)]
    z = np.r_[rng.uniform(0.05, 0.7, n // 2), rng.uniform(0.7, 80, n - n // 2)]
    cam = np.c_[(uv[:, 0] - K[0, 2]) * z / K[0, 0], (uv[:, 1] - K[1, 2]) * z / K[1, 1], z]
    velo = (cam - T[:3, 3]) @ T[:3, :3]  # T^-1: camera -> LiDAR
    for scan in (np.c_[velo, np.zeros(n)].astype(np.float32), velo.astype(np.float32)):
        kept = _cull_keeps_what_the_passes_keep(scan, calib, w, h)
        assert 0 < len(kept) < len(scan)
    empty = np.zeros((0, 4), np.float32)
    assert rows_in_view(empty, calib.P_velo_to_image2, w, h, 0.1).shape == (0, 4)


def test_view_cull_on_a_real_scan():
    """On a real 360-degree scan the passes give the same arrays with and without the cull, and
    the cull keeps under a third of the scan."""
    seq = shared_path("kitti_raw_snippet", "sequences", "r0926")
    calib = parse_calib(seq / "calib.txt")
    real = read_scan(seq / "velodyne" / "000000.bin")
    assert len(_cull_keeps_what_the_passes_keep(real, calib, 1242, 375)) < 0.3 * len(real)
