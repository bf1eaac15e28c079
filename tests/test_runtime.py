"""The torch-free runtime: ONNX trajectory = torch trajectory, resume after a kill, bad input handling."""

import importlib.util
import inspect
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, shared_path
from typer.testing import CliRunner

from cli.main import app
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.odometry import Odometry, ScanWarning
from d3lvo_deploy.pipeline import RunConfig, run_sequence
from d3lvo_deploy.poses import read_poses
from d3lvo_deploy.sequence import KittiSequence

runner = CliRunner()


def _cam2_motion_to_cam0(P2: np.ndarray):
    """By hand: x_cam2 = x_cam0 + b with b = K2^-1 p4 from P2's fourth column, so an image_2
    motion A is [I|-b] A [I|b] in cam0."""
    b = np.linalg.solve(P2[:, :3], P2[:, 3])
    to2, from2 = np.eye(4), np.eye(4)
    to2[:3, 3], from2[:3, 3] = b, -b
    return lambda A: from2 @ A @ to2


def _torch_trajectory_from_the_files(ck: Path, seq_dir: Path) -> np.ndarray:
    """The torch model fed by this test's own reading of the sequence, sharing nothing with the
    runtime but the files: PIL decodes the PNGs, calib.txt is split by hand, the view is the
    largest bottom-centre crop of the network's aspect (docs/conventions.md) resized with INTER_AREA,
    each pixel keeps its nearest LiDAR return (P2 Tr, pixel centres at integers), and each
    image_2 motion A goes to cam0 through P2's baseline b = K2^-1 p4: T = [I|-b] A [I|b]."""
    import cv2
    import torch
    from PIL import Image

    from models.checkpoint import build_model, load_checkpoint
    from models.layers import inverse_depth

    model = build_model(load_checkpoint(ck)).eval()
    w, h = model.cfg.width, model.cfg.height
    rows = {line.split(":")[0]: np.array(line.split(":")[1].split(), float)
            for line in (seq_dir / "calib.txt").read_text().splitlines() if ":" in line}
    P2, Tr = rows["P2"].reshape(3, 4), np.vstack([rows["Tr"].reshape(3, 4), [0, 0, 0, 1]])
    names = sorted(f.stem for f in (seq_dir / "image_2").glob("*.png"))
    W, H = Image.open(seq_dir / "image_2" / f"{names[0]}.png").size
    cw = min(W, int(H * w / h))
    ch = min(H, int(round(cw * h / w)))
    top, left = H - ch, (W - cw) // 2
    sx, sy = w / cw, h / ch
    fx, fy, cx, cy = P2[0, 0] * sx, P2[1, 1] * sy, (P2[0, 2] - left + 0.5) * sx - 0.5, (P2[1, 2] - top + 0.5) * sy - 0.5
    K = torch.tensor([[fx, fy, cx, cy]], dtype=torch.float32)

    def inputs(name):
        rgb = np.asarray(Image.open(seq_dir / "image_2" / f"{name}.png").convert("RGB"))[top:top + ch, left:left + cw]
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        scan = np.fromfile(seq_dir / "velodyne" / f"{name}.bin", np.float32).reshape(-1, 4)
        x = (P2 @ Tr @ np.c_[scan[:, :3].astype(float), np.ones(len(scan))].T).T
        keep = x[:, 2] > 0.1
        z = x[keep, 2]
        u = (x[keep, 0] / z - left + 0.5) * sx - 0.5
        v = (x[keep, 1] / z - top + 0.5) * sy - 0.5
        c, r = np.floor(u + 0.5).astype(int), np.floor(v + 0.5).astype(int)
        inside = (c >= 0) & (c < w) & (r >= 0) & (r < h)
        depth = np.zeros((h, w), np.float32)
        for ci, ri, zi in sorted(zip(c[inside], r[inside], z[inside]), key=lambda t: -t[2]):
            depth[ri, ci] = zi  # far to near: the nearest return is written last
        return torch.from_numpy(rgb).permute(2, 0, 1)[None], torch.from_numpy(depth)[None, None]

    to_cam0 = _cam2_motion_to_cam0(P2)
    poses, prev, motion = [np.eye(4)], None, torch.eye(4)[None]
    with torch.no_grad():
        for name in names:
            rgb, depth = inputs(name)
            feats, depths, grey = model.encode(rgb, model.complete(rgb, depth))
            cur = (feats, depths, grey, model.lidar_levels(inverse_depth(depth, model.cfg.min_depth)))
            if prev is not None:
                motion = model.flow_pose(prev[0], cur[0], prev[1], prev[2], cur[2], K, motion, prev[3], None,
                                         cur[1])["matrix"]
                poses.append(poses[-1] @ to_cam0(motion[0].double().numpy()))
            prev = cur
    return np.array(poses)


def test_onnx_trajectory_equals_torch(small_model, small_synth, tmp_path):
    """The runtime (its own reading, calibration, preprocessing, engine and frame change) against
    the torch model fed by the test's own reading of the files."""
    ck, onnx_dir = small_model
    torch_traj = _torch_trajectory_from_the_files(ck, small_synth)
    run_sequence(KittiSequence.open(small_synth), onnx_dir, RunConfig(out=tmp_path / "p.txt"))
    est = read_poses(tmp_path / "p.txt").poses
    assert est.shape == torch_traj.shape == (6, 4, 4)
    np.testing.assert_allclose(est[0], np.eye(4))
    assert np.linalg.norm(torch_traj[-1, :3, 3]) > 1.0  # the clip moves far beyond the tolerance
    assert max(np.degrees(np.arccos(np.clip((np.trace(p[:3, :3]) - 1) / 2, -1, 1))) for p in torch_traj) > 0.05
    np.testing.assert_allclose(est[:, :3, 3], torch_traj[:, :3, 3], atol=1e-5)
    np.testing.assert_allclose(est[:, :3, :3], torch_traj[:, :3, :3], atol=1e-6)


def test_streaming_api_matches_the_file(small_model, small_synth, tmp_path):
    """Each pose is the previous one times the pair's cam0 motion (KITTI's T_0k = T_0,k-1 T_k-1,k),
    where the cam0 motion is the engine's image_2 motion A moved through the rig by hand:
    x_cam2 = x_cam0 + b with b = K2^-1 p4 from P2's fourth column, so T = [I|-b] A [I|b]."""
    _, onnx_dir = small_model
    seq = KittiSequence.open(small_synth)
    run_sequence(seq, onnx_dir, RunConfig(out=tmp_path / "p.txt"))
    odo = Odometry(onnx_dir, small_synth / "calib.txt")
    odo.keep_outputs = True
    P2 = seq.calib.P2
    to_cam0 = _cam2_motion_to_cam0(P2)
    expect = [np.eye(4)]
    poses = [odo.step(seq.image(0), seq.scan(0))]
    for i in range(1, len(seq)):
        poses.append(odo.step(seq.image(i), seq.scan(i)))
        A = odo.last["flowpose"]["matrix"][0].astype(np.float64)
        expect.append(expect[-1] @ to_cam0(A))
    assert max(np.degrees(np.arccos(np.clip((np.trace(p[:3, :3]) - 1) / 2, -1, 1))) for p in expect) > 0.01
    np.testing.assert_allclose(np.array(poses), np.array(expect), atol=1e-9)
    np.testing.assert_array_equal(np.array(poses)[:, :3], read_poses(tmp_path / "p.txt").poses[:, :3])
    odo.reset()
    np.testing.assert_array_equal(odo.step(seq.image(3), seq.scan(3)), np.eye(4))


def test_streaming_api_refuses_what_would_give_wrong_poses(small_model, small_synth):
    """Inputs that would otherwise run to a wrong trajectory, NaN poses or a failure frames later
    are one D3LVOInputError at the call: a transposed scan, a scan in millimetres or in float64,
    images of another size than the calibration's, a LiDAR extrinsic that sees nothing, non-rigid
    or NaN poses for reset/prime, NaN, inf or non-number stamps, and wrong argument types."""
    from d3lvo_deploy.calib import Calib
    from d3lvo_deploy.direct import DirectOdometry

    _, onnx_dir = small_model
    seq = KittiSequence.open(small_synth)
    img, scan = seq.image(0), seq.scan(0)
    fresh = lambda calib=small_synth / "calib.txt": Odometry(onnx_dir, calib)  # noqa: E731
    mm = scan.copy()
    mm[:, :3] *= 1000.0
    cases = [(lambda: fresh().step(img, scan.T), "transposed"),
             (lambda: fresh().step(img, mm), "must be in metres"),
             # a float64 scan of float32 values, and one of full float64 values (+ 1/3), read as float32
             (lambda: fresh().step(img, scan.astype(np.float64).view(np.float32).reshape(-1, 4)),
              "LiDAR returns have a coordinate beyond 1,000 km: a scan must be float32 x, y, z, reflectance"),
             (lambda: fresh().step(img, (scan.astype(np.float64) + 1 / 3).view(np.float32).reshape(-1, 4)),
              "LiDAR returns have a coordinate beyond 1,000 km: a scan must be float32 x, y, z, reflectance"),
             (lambda: fresh().step(np.ascontiguousarray(img[:90, :300]), scan), "lies outside frame 0's 300x90 image"),
             (lambda: fresh(Calib(seq.calib.P2, np.eye(4))).step(img, scan), "none of the"),
             (lambda: fresh().step(None, scan), "got NoneType"),
             (lambda: fresh().step(img, [["a", "b", "c"]]), "numeric (N,4) array"),
             (lambda: fresh().step(img, scan[:100].astype(str)), "numeric (N,4) array (x, y, z, intensity), got an array of <U"),
             (lambda: fresh({"P2": seq.calib.P2}), "calib must be a Calib or the path"),
             (lambda: Calib(seq.calib.P2[:, :3], seq.calib.Tr), "P2 must be a 3x4"),
             (lambda: Calib(seq.calib.P2, np.full((4, 4), np.nan)), "finite"),
             (lambda: fresh().reset(np.full((4, 4), np.nan)), "start_pose has NaN"),
             (lambda: fresh().reset(np.eye(3)), "start_pose must be a 4x4"),
             (lambda: fresh().reset(np.diag([2.0, 1.0, 1.0, 1.0])), "not a rigid transform"),
             (lambda: fresh().prime(img, scan, np.eye(4), previous_pose=np.full((4, 4), np.nan)), "previous_pose"),
             (lambda: fresh().prime(img, scan, np.eye(4), hold_left=5), "prime's hold_left must be a whole number"),
             # a frame's time: NaN or inf would reach the constant-velocity start as NaN or a huge scale
             (lambda: fresh().step(img, scan, float("inf")), "stamp must be a finite time in seconds, not inf"),
             (lambda: fresh().step(img, scan, "0.1"), "stamp must be a time in seconds (a number), not '0.1'"),
             (lambda: DirectOdometry(seq.calib).step(img, scan, float("nan")), "stamp must be a finite time"),
             (lambda: fresh().prime(img, scan, np.eye(4), stamp=[0.1]), "prime's stamp must be a time in seconds")]
    for call, words in cases:
        with pytest.raises(D3LVOInputError, match=words.replace("(", r"\(").replace(")", r"\)")):
            call()
    odo = fresh()  # the same frame, right: the tracker takes it
    np.testing.assert_array_equal(odo.step(img, scan), np.eye(4))
    with pytest.warns(ScanWarning, match="keeps that pair's starting motion"):  # None: no scan, said so
        odo.step(seq.image(1), None)


def test_real_frames_give_20_finite_poses(small_model, tmp_path):
    _, onnx_dir = small_model
    seq = KittiSequence.open(shared_path("kitti_raw_snippet", "sequences", "r0926"))
    run_sequence(seq, onnx_dir, RunConfig(out=tmp_path / "real.txt"))
    p = read_poses(tmp_path / "real.txt").poses
    assert p.shape == (20, 4, 4) and np.all(np.isfinite(p))
    np.testing.assert_allclose(p[0], np.eye(4))


def test_resume_after_partial_run_is_identical(small_model, small_synth, tmp_path):
    _, onnx_dir = small_model
    seq = KittiSequence.open(small_synth)
    run_sequence(seq, onnx_dir, RunConfig(out=tmp_path / "full.txt"))
    run_sequence(seq, onnx_dir, RunConfig(out=tmp_path / "part.txt", end=3))
    with open(tmp_path / "part.txt", "a") as fh:
        fh.write("0.5 0.1 0")  # a line cut mid-write by the interruption
    s = run_sequence(seq, onnx_dir, RunConfig(out=tmp_path / "part.txt", resume=True))
    assert s.resumed_from == 3
    assert (tmp_path / "part.txt").read_text() == (tmp_path / "full.txt").read_text()


@pytest.mark.parametrize("which", ["bundled", "chained"])
def test_resume_restores_the_start_a_graph_keeps_of_its_own(which, small_synth, tmp_path, request):
    """The bundled graph starts each pair from its weighted pose (`start_next`), which the pose it
    keeps need not be, so the poses alone cannot tell a resumed run where to start: the run saves
    each frame's start beside the poses (the same as the API's `Odometry.start_state()` after that
    frame), and a resumed run reads it back and writes what the uninterrupted run wrote. Without
    that file it warns and still finishes. A graph whose classical solve starts from its own
    previous pose (`pt_classical_chain`, `scan_judge_model`) is fed that pose (`classical_next`)
    and saves both starts on each line."""
    from d3lvo_deploy.bundled import bundled_model_dir
    from d3lvo_deploy.geometry import change_frame
    from d3lvo_deploy.pipeline import start_file

    model = bundled_model_dir() if which == "bundled" else request.getfixturevalue("scan_judge_model")[1]
    seq = KittiSequence.open(small_synth)
    odo = Odometry(model, seq.calib)
    assert odo.keeps_own_start and odo.chains_classical == (which == "chained")
    odo.keep_outputs = True
    fed, run = [], odo.model.run  # where each pair's classical solve started, in whichever graph solved it
    odo.model.run = lambda stage, feeds: (fed.append(feeds.get("classical_start", feeds.get("init_pose")))
                                          if stage in ("flowpose", "classical") and "classical_pose" not in feeds
                                          else None, run(stage, feeds))[1]
    starts, kept = [], []
    for i in range(len(seq)):
        odo.step(seq.image(i), seq.scan(i))
        if i:  # the runtime starts the next pair where the graph says, not from the kept pose's motion
            out = odo.last["flowpose"]
            want = [out["start_next"][0]] + ([out["classical_next"][0]] if odo.chains_classical else [])
            np.testing.assert_allclose(odo.start_state(), np.stack(want), atol=1e-7)
            if odo.hold:  # the graph says which pose it kept, and the runtime holds the weighted one
                kept.append(bool(out["select_kept"][0] > 0.5))
                np.testing.assert_allclose(out["matrix"][0], out["start_next" if kept[-1] else "classical_next"][0],
                                           atol=1e-6)
                used = out["start_next"][0] if kept[-1] or kept[-2:-1] == [True] else out["classical_next"][0]
                np.testing.assert_allclose(odo.relative, change_frame(used.astype(np.float64), seq.calib.T_cam0_cam2),
                                           atol=1e-6)
            if i > 1:  # the classical solve started where the previous pair left it
                np.testing.assert_allclose(fed[-1][0][:3], starts[-1][:len(odo.start_state()) * 12].reshape(-1, 3, 4)[-1],
                                           atol=1e-7)
        # (and, where the model holds its choice, `pt_select_hold`, the count left at the end)
        starts.append(np.r_[odo.start_state()[:, :3].reshape(-1), [odo.hold_left] if odo.hold else []])
    assert len(fed) == len(seq) - 1
    print("weighted pose kept by the graph on pairs", kept)
    if odo.hold:  # `scan_judge_model` holds 1 pair: a kept pair followed by one it did not keep
        assert any(a and not b for a, b in zip(kept, kept[1:])), kept
    if odo.chains_classical:  # the two starts differ, so feeding the weighted one would show
        assert max(np.abs(s[:12] - s[12:24]).max() for s in starts) > 1e-6
    full, part = tmp_path / "full.txt", tmp_path / "part.txt"
    run_sequence(seq, model, RunConfig(out=full))
    saved = np.loadtxt(start_file(full))
    np.testing.assert_allclose(saved, np.array(starts), atol=1e-7)
    run_sequence(seq, model, RunConfig(out=part, end=3))
    with open(start_file(part), "a") as fh:  # stopped after saving frame 3's start, before its pose
        fh.write(start_file(full).read_text().splitlines()[3] + "\n")
    s = run_sequence(seq, model, RunConfig(out=part, resume=True))
    assert s.resumed_from == 3 and part.read_text() == full.read_text()
    assert start_file(part).read_text() == start_file(full).read_text()
    run_sequence(seq, model, RunConfig(out=part, end=3, overwrite=True))
    start_file(part).unlink()
    with pytest.warns(UserWarning, match="saved starts are missing"):
        s = run_sequence(seq, model, RunConfig(out=part, resume=True))
    assert s.resumed_from == 3 and len(read_poses(part)) == len(seq)


def test_killed_run_resumes_to_the_same_file(small_model, small_synth, tmp_path):
    """A real SIGKILL after exactly 3 poses, then --resume. The run is paced by times.txt
    (--realtime) and frame 3 is stamped 1000 s later, so it is asleep with 3 poses written when
    the kill comes, however fast or slow the machine."""
    _, onnx_dir = small_model
    seq_dir = tmp_path / "seq"
    shutil.copytree(small_synth, seq_dir)
    stamps = [0.0, 0.1, 0.2, 1000.0, 1000.1, 1000.2]
    (seq_dir / "times.txt").write_text("".join(f"{t:.6e}\n" for t in stamps))
    full = tmp_path / "full.txt"
    assert runner.invoke(app, ["run", "--seq-dir", str(seq_dir), "--onnx", str(onnx_dir), "--out", str(full)]).exit_code == 0
    out = tmp_path / "killed.txt"
    cmd = [sys.executable, "-m", "cli.main", "run", "--seq-dir", str(seq_dir), "--onnx", str(onnx_dir), "--out", str(out)]
    proc = subprocess.Popen(cmd + ["--realtime"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and (not out.exists() or out.read_text().count("\n") < 3) and proc.poll() is None:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert out.read_text().count("\n") == 3
    r = subprocess.run(cmd + ["--resume"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "resuming after 3 poses" in r.stdout + r.stderr
    assert out.read_text() == full.read_text()


def test_a_tum_file_resumes_within_micrometres(small_model, small_synth, tmp_path):
    """TUM poses are read back from their quaternions, not bit for bit: a resumed run continues
    within a few micrometres of the uninterrupted one (docs/runtime.md; this untrained test model's
    solver is far from converged, which carries the last bits on further), the times the same."""
    _, onnx_dir = small_model
    base = ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--pose-format", "tum", "--backend",
            "onnxruntime"]
    assert runner.invoke(app, [*base, "--out", str(tmp_path / "full.txt")]).exit_code == 0
    assert runner.invoke(app, [*base, "--out", str(tmp_path / "part.txt"), "--end", "3"]).exit_code == 0
    r = runner.invoke(app, [*base, "--out", str(tmp_path / "part.txt"), "--resume"])
    assert r.exit_code == 0 and "resuming after 3 poses" in r.output, r.output
    full, part = read_poses(tmp_path / "full.txt"), read_poses(tmp_path / "part.txt")
    assert len(full) == len(part) == 6 and np.array_equal(full.timestamps, part.timestamps)
    assert np.abs(full.poses[:, :3, 3] - part.poses[:, :3, 3]).max() < 1e-5
    assert np.linalg.norm(full.poses[-1, :3, 3]) > 1.0  # the clip moves: the bound is not vacuous


def _sliced_copy(seq_dir, out, start: int, end: int):
    """Frames start..end-1 of a KITTI folder as a sequence of their own (renumbered from 0)."""
    import shutil

    for sub, ext in (("image_2", "png"), ("velodyne", "bin")):
        (out / sub).mkdir(parents=True)
        for k, i in enumerate(range(start, end)):
            shutil.copy(seq_dir / sub / f"{i:06d}.{ext}", out / sub / f"{k:06d}.{ext}")
    shutil.copy(seq_dir / "calib.txt", out / "calib.txt")
    times = (seq_dir / "times.txt").read_text().split()[start:end]
    (out / "times.txt").write_text("\n".join(times) + "\n")
    return out


def _tum_by_hand(path) -> tuple[np.ndarray, np.ndarray]:
    """TUM lines 'stamp tx ty tz qx qy qz qw' -> stamps and 4x4 poses, with the textbook
    unit-quaternion rotation matrix (written here, not the project's reader)."""
    stamps, poses = [], []
    for line in path.read_text().splitlines():
        s, tx, ty, tz, x, y, z, w = map(float, line.split())
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, (tx, ty, tz)
        stamps.append(s)
        poses.append(T)
    return np.array(stamps), np.array(poses)


def test_frame_range_and_tum(small_model, small_synth, tmp_path):
    """--start 2 --end 5 in TUM is a run of its own from frame 2 (the Gauss-Newton head starts its
    first pair from rest): the same poses as a KITTI-format run over a folder holding only frames
    2-4, and the stamps of those frames; resuming that range after frame 3 changes nothing."""
    _, onnx_dir = small_model
    seq = KittiSequence.open(small_synth)
    run_sequence(seq, onnx_dir, RunConfig(out=tmp_path / "r.tum", fmt="tum", start=2, end=5))
    stamps, tum = _tum_by_hand(tmp_path / "r.tum")
    np.testing.assert_allclose(stamps, [0.2, 0.3, 0.4], atol=1e-6)
    sliced = KittiSequence.open(_sliced_copy(small_synth, tmp_path / "sliced", 2, 5))
    run_sequence(sliced, onnx_dir, RunConfig(out=tmp_path / "sliced.txt"))
    kitti = np.loadtxt(tmp_path / "sliced.txt").reshape(-1, 3, 4)
    np.testing.assert_allclose(tum[:, :3], kitti, atol=1e-6)  # TUM prints 6-9 digits
    run_sequence(seq, onnx_dir, RunConfig(out=tmp_path / "part.txt", start=2, end=4))
    run_sequence(seq, onnx_dir, RunConfig(out=tmp_path / "part.txt", start=2, end=5, resume=True))
    np.testing.assert_allclose(np.loadtxt(tmp_path / "part.txt").reshape(-1, 3, 4), kitti, atol=1e-9)


def test_scan_fallbacks_warn(small_model, small_synth):
    _, onnx_dir = small_model
    seq = KittiSequence.open(small_synth)
    odo = Odometry(onnx_dir, seq.calib)
    odo.step(seq.image(0), seq.scan(0))
    bad = seq.scan(1).copy()
    bad[::3, 0] = np.nan
    with pytest.warns(ScanWarning, match="NaN"):
        p = odo.step(seq.image(1), bad)
    with pytest.warns(ScanWarning, match="no LiDAR points"):
        p = odo.step(seq.image(2), np.zeros((0, 4), np.float32))
    with pytest.warns(ScanWarning, match=r"integer coordinates \(int32\)"):  # whole metres: said, then used
        odo.step(seq.image(3), seq.scan(3).astype(np.int32))
    assert np.all(np.isfinite(p))
    with pytest.raises(D3LVOInputError, match="earlier frames were 620x188"):
        odo.step(np.zeros((100, 200, 3), np.uint8), seq.scan(4))


def test_nan_reflectance_is_read_as_zero(small_model, small_synth):
    """Nothing reads a scan's reflectance, but the view cull multiplies whole rows (0 x NaN is NaN):
    a scan whose reflectance is NaN or inf gives the poses of the same scan with reflectance 0, on
    the network and on the direct tracker, without a warning; the caller's scan stays as given."""
    from d3lvo_deploy.direct import DirectOdometry

    _, onnx_dir = small_model
    seq = KittiSequence.open(small_synth)
    scans = [seq.scan(i) for i in range(3)]
    for scan in scans:
        assert scan[:, 3].any()  # a reflectance to lose
    broken = [s.copy() for s in scans]
    for s in broken:
        s[::2, 3], s[1::2, 3] = np.nan, np.inf
    zero = [np.concatenate([s[:, :3], np.zeros_like(s[:, 3:])], 1) for s in scans]
    for make in (lambda: Odometry(onnx_dir, seq.calib), lambda: DirectOdometry(seq.calib)):
        poses = {}
        for name, given in (("zero", zero), ("broken", broken)):
            tracker = make()
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                poses[name] = np.array([tracker.step(seq.image(i), given[i]) for i in range(3)])
        assert np.linalg.norm(poses["zero"][-1][:3, 3]) > 0.1  # it moved
        np.testing.assert_array_equal(poses["broken"], poses["zero"])
    assert np.isnan(broken[0][0, 3]) and np.isinf(broken[0][1, 3])  # the caller's arrays untouched


def test_a_blank_frame_warns_and_keeps_the_starting_motion(small_synth):
    """A black frame mid-run (a camera fault) leaves the point solver nothing to track: the pairs
    with it keep their starting motion (`motion2`, the constant-velocity start), and the tracker
    says so, naming the frame; a scan in millimetres later on is named as the scan's fault; the
    bundled model and the direct tracker alike."""
    from d3lvo_deploy.bundled import bundled_model_dir
    from d3lvo_deploy.direct import DirectOdometry
    from d3lvo_deploy.geometry import change_frame

    seq = KittiSequence.open(small_synth)
    for make in (lambda: Odometry(bundled_model_dir(), seq.calib), lambda: DirectOdometry(seq.calib)):
        tracker = make()
        rel = []
        for i in range(3):
            tracker.scan_source = f"frame {i}'s scan"
            image = seq.image(i) if i < 2 else np.zeros_like(seq.image(i))
            start = change_frame(tracker.motion2, seq.calib.T_cam0_cam2)  # where pair (i-1, i) starts
            if i < 2:
                with warnings.catch_warnings():
                    warnings.simplefilter("error")
                    tracker.step(image, seq.scan(i))
            else:
                blank = "frame 2's image: no texture where the scan's .* returns in and around it land"
                with pytest.warns(ScanWarning, match=blank):
                    tracker.step(image, seq.scan(i))
            rel.append(tracker.relative.copy())
        assert np.linalg.norm(rel[1][:3, 3]) > 0.1  # it moved
        np.testing.assert_allclose(rel[2], start, atol=1e-6)  # the black frame's pair: its starting motion
        # a scan in millimetres after the first frame (which alone is checked for units) is blamed
        # on the scan, not on the image; after a reset the next frame is a first frame again
        mm = seq.scan(3) * np.array([1000.0, 1000.0, 1000.0, 1.0], np.float32)
        tracker.scan_source = "frame 3's scan"
        with pytest.warns(ScanWarning, match=r"frame 3's scan: 0 of its \d+ returns in and around the view lie "
                                             r"within .* m of the camera: not in metres \(millimetres\?\)"):
            tracker.step(seq.image(3), mm)
        tracker.reset()
        with pytest.raises(D3LVOInputError, match="must be in metres"):
            tracker.step(seq.image(3), mm)


@pytest.mark.parametrize("breakage, words", [
    (lambda d: (d / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: 1 0 0 0 0 1 0 0 0 0 1 0\n"), ["calib.txt", "P2"]),
    (lambda d: (d / "calib.txt").write_text((d / "calib.txt").read_text().replace("Tr:", "Xx:")), ["calib.txt", "LiDAR extrinsic"]),
    (lambda d: (d / "image_2" / "000004.png").write_bytes(b"garbage"), ["000004.png", "--resume", "frames 0..3"]),
    (lambda d: (d / "velodyne" / "000002.bin").write_bytes(b"\0" * 10), ["000002.bin", "truncated"]),
    (lambda d: np.fromfile(d / "velodyne" / "000000.bin", np.float32).astype(np.float64).tofile(
        d / "velodyne" / "000000.bin"), ["000000.bin", "a float64 file reads like this"]),
    (lambda d: [(d / "velodyne" / "000003.bin").unlink(), (d / "image_2" / "000003.png").unlink()], ["missing frame"]),
    (lambda d: [(d / "times.txt").unlink(), (d / "times.txt").mkdir()], ["times.txt: is a folder"]),
    (lambda d: [(d / "calib.txt").unlink(), (d / "calib.txt").mkdir()], ["calib.txt: is a folder"]),
])
def test_cli_bad_input(small_model, small_synth, tmp_path, breakage, words):
    _, onnx_dir = small_model
    d = tmp_path / "seq"
    shutil.copytree(small_synth, d)
    breakage(d)
    r = runner.invoke(app, ["run", "--seq-dir", str(d), "--onnx", str(onnx_dir), "--out", str(tmp_path / "o.txt")])
    assert r.exit_code == 1, r.output
    assert "Traceback" not in r.output
    for w in words:
        assert w in r.output


@pytest.mark.parametrize("extra", [[], ["--pipeline"], ["--pipeline", "--threads", "2", "--backend", "onnxruntime"],
                                   ["--method", "direct"]])
def test_cli_frame_of_another_size(small_model, small_synth, tmp_path, extra):
    """A frame unlike the others (another camera's size) stops the run with the frame named and the
    poses before it kept: sequential, read ahead (two deep), read and encoded ahead (three deep,
    onnxruntime on two threads), and the direct tracker; never a pose of it."""
    import cv2

    _, onnx_dir = small_model
    d = tmp_path / "seq"
    shutil.copytree(small_synth, d)
    cv2.imwrite(str(d / "image_2" / "000004.png"), np.zeros((100, 300, 3), np.uint8))
    r = runner.invoke(app, ["run", "--seq-dir", str(d), "--onnx", str(onnx_dir), "--out", str(tmp_path / "o.txt"),
                            *extra])
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    for w in ("image_2/000004.png: image is 300x100, earlier frames were 620x188", "frames 0..3", "--resume"):
        assert w in r.output, r.output
    assert len((tmp_path / "o.txt").read_text().splitlines()) == 4


def test_cli_run_scores_with_gt_and_plots(small_model, small_synth, tmp_path):
    _, onnx_dir = small_model
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out", str(tmp_path / "o.txt"),
                            "--plot", str(tmp_path / "t.png")])
    assert r.exit_code == 0, r.output
    assert "ATE m" in r.output and "flowpose" in r.output
    assert (tmp_path / "t.png").stat().st_size > 1000


def test_cli_run_of_one_frame_with_ground_truth_writes_it_and_scores_nothing(small_model, small_synth, tmp_path):
    """One frame is a run (its pose, identity, written; exit 0), and too short to score: said in a
    line, no metrics, as a run without ground truth."""
    _, onnx_dir = small_model
    assert (small_synth / "poses.txt").is_file()
    r = runner.invoke(app, ["run", str(small_synth), "--onnx", str(onnx_dir), "--start", "3", "--end", "4",
                            "--out-dir", str(tmp_path / "res")])
    assert r.exit_code == 0 and "Traceback" not in r.output, r.output
    assert "1 pose: too few to score against the ground truth (2 at least): no metrics" in r.output
    np.testing.assert_array_equal(read_poses(tmp_path / "res" / "poses.txt").poses, np.eye(4)[None])
    assert not (tmp_path / "res" / "metrics.json").exists()
    if importlib.util.find_spec("matplotlib") is not None:  # the plot of what was written, as without ground truth
        assert (tmp_path / "res" / "trajectory.png").stat().st_size > 1000


def test_kitti_root_layout(small_model, small_synth, tmp_path):
    _, onnx_dir = small_model
    root = tmp_path / "kitti"
    shutil.copytree(small_synth, root / "sequences" / "09")
    (root / "poses").mkdir()
    shutil.move(root / "sequences" / "09" / "poses.txt", root / "poses" / "09.txt")
    r = runner.invoke(app, ["run", "--kitti-root", str(root), "--sequence", "09", "--onnx", str(onnx_dir),
                            "--out", str(tmp_path / "09.txt")])
    assert r.exit_code == 0, r.output
    assert "ATE m" in r.output


def test_provider_fallback_warns(small_model):
    from d3lvo_deploy.onnx_model import resolve_providers

    _, onnx_dir = small_model
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        provs = resolve_providers("tensorrt")
    import onnxruntime as ort

    if "TensorrtExecutionProvider" not in ort.get_available_providers():
        assert provs == ["CPUExecutionProvider"] and "falling back" in str(w[0].message)
    with pytest.raises(D3LVOInputError, match="--provider"):
        resolve_providers("tpu")


def test_rerun_never_discards_saved_poses(small_model, small_synth, tmp_path):
    _, onnx_dir = small_model
    out = tmp_path / "p.txt"
    args = ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out", str(out), "--end", "3"]
    assert runner.invoke(app, args).exit_code == 0
    saved = out.read_text()
    r = runner.invoke(app, args)
    assert r.exit_code == 1 and "already holds 3 poses" in r.output and "--resume" in r.output and "--overwrite" in r.output
    assert out.read_text() == saved
    r = runner.invoke(app, args[:-2] + ["--overwrite"])
    assert r.exit_code == 0 and len(out.read_text().splitlines()) == 6


def test_run_checks_arguments_before_any_work(small_model, small_synth, tmp_path):
    """A bad argument is one error before the progress bar draws, and nothing is written."""
    import re

    ck, onnx_dir = small_model
    p = str(tmp_path / "p.txt")
    cases = [(["--out", str(tmp_path)], "is a folder"),
             (["--out", p, "--pose-format", "xyz"], "--pose-format must be kitti or tum"),
             (["--out", p, "--format", "xyz"], "--format must be auto or one of"),
             (["--out", p, "--onnx", str(ck)], "d3lvo export --ckpt"),
             (["--out", p, "--onnx", str(onnx_dir / "encoder.onnx")], "one ONNX file"),
             (["--out", p, "--backend", "tvm"], "--backend must be one of")]
    for extra, words in cases:
        args = ["run", "--seq-dir", str(small_synth)] + (["--onnx", str(onnx_dir)] if "--onnx" not in extra else [])
        r = runner.invoke(app, args + extra)
        assert r.exit_code == 1 and words in r.output, (extra, r.output)
        assert not re.search(r"\s0/\d+\s", r.output), r.output  # no "0/6" of a progress bar
        assert not (tmp_path / "p.txt").exists()


def test_format_is_case_insensitive_and_a_finished_file_says_so(small_model, small_synth, tmp_path):
    _, onnx_dir = small_model
    args = ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out", str(tmp_path / "p.tum"),
            "--pose-format", "TUM"]
    assert runner.invoke(app, args).exit_code == 0
    assert len(read_poses(tmp_path / "p.tum", fmt="tum")) == len(KittiSequence.open(small_synth))
    saved = (tmp_path / "p.tum").read_text()
    r = runner.invoke(app, args + ["--resume"])
    assert r.exit_code == 0 and "already holds all 6 poses" in r.output and "nothing to run" in r.output
    assert "latency per frame" not in r.output  # no empty table
    assert (tmp_path / "p.tum").read_text() == saved


def test_demo_writes_outside_the_checkout():
    from cli.demo_cmd import demo_command

    default = inspect.signature(demo_command).parameters["out_dir"].default.default
    assert not Path(default).resolve().is_relative_to(ROOT)


def test_viz_writes_a_panel_per_chosen_frame(small_model, small_synth, tmp_path):
    import cv2

    from d3lvo_deploy.viz import BAR, flow_to_rgb

    _, onnx_dir = small_model
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out", str(tmp_path / "p.txt"),
                            "--viz", str(tmp_path / "viz"), "--viz-every", "2"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "viz").iterdir()) == ["000002.png", "000004.png"]
    assert "no picture" not in r.output
    # six frames and the default --viz-every 10: pictures of frames 10, 20, ..., so none, and it says so
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out", str(tmp_path / "q.txt"),
                            "--viz", str(tmp_path / "none")])
    assert r.exit_code == 0 and "--viz draws frames 10, 20, ... of a run (--viz-every 10), and this one has 6 frames: " \
        "no picture" in r.output, r.output
    # --viz naming a file: one line before the first frame, nothing written
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out", str(tmp_path / "f.txt"),
                            "--viz", str(tmp_path / "p.txt"), "--viz-every", "1"])
    assert r.exit_code == 1 and "p.txt: is a file; --viz names the folder for the pictures" in r.output, r.output
    assert not (tmp_path / "f.txt").exists()
    img = cv2.imread(str(tmp_path / "viz" / "000002.png"))
    h, w = 64, 224  # the test model's network view
    assert img.shape == (5 * (h + BAR), w, 3)  # camera, LiDAR, completion, flow, confidence
    # the flow coding: rightward flow is red, leftward cyan, no flow white
    f = np.zeros((2, 1, 3), np.float32)
    f[0, 0, 0], f[0, 0, 2] = 1.0, -1.0
    rgb = flow_to_rgb(f, 1.0)[0]
    assert tuple(rgb[0]) == (255, 0, 0) and tuple(rgb[1]) == (255, 255, 255) and tuple(rgb[2]) == (0, 255, 255)


@pytest.mark.skipif(importlib.util.find_spec("rerun") is None, reason="the [rerun] extra is not installed")
def test_rerun_recording_holds_the_run(small_model, small_synth, tmp_path):
    """The .rrd holds a trajectory row and a scan per frame, ending on the poses written, and the
    network's pictures on the --viz-every frames only."""
    import rerun.chunk as rc

    _, onnx_dir = small_model
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out", str(tmp_path / "p.txt"),
                            "--rerun", str(tmp_path / "run.rrd"), "--viz-every", "2"])
    assert r.exit_code == 0, r.output
    rows: dict[str, int] = {}
    last_strip = None
    for ch in rc.RrdReader(tmp_path / "run.rrd").stream().to_chunks():
        rows[ch.entity_path] = rows.get(ch.entity_path, 0) + ch.num_rows
        if ch.entity_path == "/world/trajectory":
            last_strip = ch.to_record_batch().column("LineStrips3D:strips").to_pylist()[-1][0]
    n = len(KittiSequence.open(small_synth))
    assert rows["/world/trajectory"] == rows["/world/lidar"] == n
    for entity in ("/world/camera/image", "/world/camera/lidar_depth", "/completed_depth", "/flow", "/confidence"):
        assert rows[entity] == 2, (entity, rows)  # frames 2 and 4
    poses = read_poses(tmp_path / "p.txt").poses
    np.testing.assert_allclose(np.array(last_strip), poses[:, :3, 3], atol=1e-5)
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out", str(tmp_path / "q.txt"),
                            "--rerun", str(tmp_path)])
    assert r.exit_code == 1 and "is a folder" in r.output and not (tmp_path / "q.txt").exists()
    # another run's recording is not replaced unasked, and the run stops before it starts
    before = (tmp_path / "run.rrd").read_bytes()
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--onnx", str(onnx_dir), "--out", str(tmp_path / "q.txt"),
                            "--rerun", str(tmp_path / "run.rrd")])
    assert r.exit_code == 1 and "already holds a Rerun recording; --overwrite" in r.output, r.output
    assert (tmp_path / "run.rrd").read_bytes() == before and not (tmp_path / "q.txt").exists()
    # a recording in a folder not made yet: made, and the output names the recording
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--method", "direct", "--out", str(tmp_path / "d.txt"),
                            "--rerun", str(tmp_path / "new" / "d.rrd")])
    assert r.exit_code == 0 and (tmp_path / "new" / "d.rrd").stat().st_size > 0, r.output
    assert f"Rerun recording in {tmp_path / 'new' / 'd.rrd'}" in r.output
    # a resumed run (the same command with --resume) records beside the interrupted run's recording
    first = (tmp_path / "new" / "d.rrd").read_bytes()
    lines = (tmp_path / "d.txt").read_text().splitlines(keepends=True)
    (tmp_path / "d.txt").write_text("".join(lines[:2]))  # as a run stopped after two poses leaves it
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--method", "direct", "--out", str(tmp_path / "d.txt"),
                            "--rerun", str(tmp_path / "new" / "d.rrd"), "--resume"])
    assert r.exit_code == 0 and f"Rerun recording in {tmp_path / 'new' / 'd-resumed.rrd'}" in r.output, r.output
    assert (tmp_path / "new" / "d.rrd").read_bytes() == first and (tmp_path / "new" / "d-resumed.rrd").stat().st_size
    assert len((tmp_path / "d.txt").read_text().splitlines()) == len(lines)


def test_readme_api_example_runs_as_pasted(monkeypatch, capsys):
    """The README's streaming-API block, executed verbatim from the checkout root."""
    text = (ROOT / "README.md").read_text()
    start = text.index("from d3lvo_deploy.bundled import bundled_model_dir")
    code = text[start:text.index("```", start)]
    monkeypatch.chdir(ROOT)
    exec(compile(code, "README.md", "exec"), {})
    printed = capsys.readouterr().out.strip().splitlines()
    assert len(printed) == 3 and "flowpose" in printed[-1]
    assert printed[0].startswith("[0. 0. 0.]")  # the first frame is the origin


@pytest.mark.parametrize("backend, how", [("onnxruntime", "encoding the next frame beside the flow+pose stage"),
                                          ("openvino", "projecting the next frame beside the network")])
def test_pipelined_run_writes_the_sequential_poses(small_model, small_synth, tmp_path, backend, how, monkeypatch):
    """Frame t+1 read and projected on a second thread while the network works on frame t (on
    onnxruntime also completed and encoded there, beside frame t's flow+pose stage): the same
    bytes as one frame at a time, and the output says which it did."""
    import threading

    if backend == "openvino":
        pytest.importorskip("openvino")
    _, onnx_dir = small_model
    ran_on = {"prepare": set(), "encode_timed": set()}  # the threads each part of a frame ran on
    for name in ran_on:
        real = getattr(Odometry, name)

        def spy(self, *args, _real=real, _name=name, **kwargs):
            thread = threading.current_thread().name.split("_")[0]
            ran_on[_name].add(thread)
            if _name == "prepare" and thread == "d3lvo-read":  # one core beside the network: one thread
                assert kwargs.get("threads") == 1
            return _real(self, *args, **kwargs)

        monkeypatch.setattr(Odometry, name, spy)
    outs = {}
    for flag in ("--pipeline", "--no-pipeline"):
        out = tmp_path / f"{flag}.txt"
        r = runner.invoke(app, ["run", str(small_synth), "--onnx", str(onnx_dir), "--out", str(out), "--backend",
                                backend, "--threads", "2", flag])  # two threads to split, whatever the test worker has
        assert r.exit_code == 0, r.output
        assert (how in r.output) == (flag == "--pipeline"), r.output
        outs[flag] = out.read_bytes()
        if flag == "--pipeline":  # the reader prepared frames, and three deep encoded them too
            assert "d3lvo-read" in ran_on["prepare"]
            assert ("d3lvo-read" in ran_on["encode_timed"]) == (backend == "onnxruntime")
    assert outs["--pipeline"] == outs["--no-pipeline"]


def test_frame_preparation_holds_blas_to_one_thread(small_model, small_synth, monkeypatch):
    """The projection's numpy products run on one BLAS thread (`d3lvo_deploy.blas`): OpenBLAS's
    workers spin after a threaded call and would take a core from the engine for the rest of the
    frame. The caller's own setting is back afterwards."""
    from threadpoolctl import threadpool_info, threadpool_limits

    from d3lvo_deploy import odometry

    _, onnx_dir = small_model
    seq = KittiSequence.open(small_synth)
    odo = Odometry(onnx_dir, seq.calib)
    seen = []
    real = odometry.rows_in_view

    def spy(*args, **kwargs):
        seen.append([lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"])
        return real(*args, **kwargs)

    monkeypatch.setattr(odometry, "rows_in_view", spy)
    with threadpool_limits(limits=2, user_api="blas"):
        odo.prepare(seq.image(0), seq.scan(0))
        after = [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]
    assert seen and seen[0] and all(n == 1 for n in seen[0]), seen
    assert after and all(n == 2 for n in after), after


def test_demo_checks_its_model_before_rendering(tmp_path):
    r = runner.invoke(app, ["demo", "--onnx", str(tmp_path / "none"), "--frames", "2", "--out", str(tmp_path / "o")])
    assert r.exit_code == 1 and "none: model folder not found" in r.output, r.output
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("resumed_from, slowest, words", [
    (0, 1, "the engines warming up; the first pair also tries the cold start's starting motions"),
    (1, 0, "the first pair also tries the cold start"),  # resumed after one pose: no motion to start from
    (3, 1, "the engines warming up)"),  # resumed after two or more: the motion is known, no cold start
    (0, 5, None)])  # a slow frame later in the run: nothing to explain it away
def test_the_latency_table_says_when_its_slowest_frame_is_a_first_one(resumed_from, slowest, words):
    from rich.console import Console

    from cli.run_cmd import latency_table
    from d3lvo_deploy.pipeline import RunSummary

    total = [40.0] * 8
    total[slowest] = 400.0
    s = RunSummary(frames=8 + resumed_from, out=Path("p.txt"), resumed_from=resumed_from, latencies_ms={"total": total})
    console = Console(width=400, record=True)
    console.print(latency_table(s))
    text = " ".join(console.export_text().split())  # the caption wraps at the table's width
    if words is None:
        assert "max:" not in text
    else:
        assert words in text and ("cold start" in text) == (resumed_from <= 1), text
