"""Input formats: ROS 1 / ROS 2 bags, KITTI raw drives and plain folders give the poses of the
same frames read from a KITTI odometry folder; bad recordings fail in one line, writing nothing;
a results folder's config.toml repeats its run exactly.

The recordings are written by the tests themselves (tests/recordings.py) with the formats' own
writers (rosbags, pypcd4, plyfile), never with the readers under test."""

from __future__ import annotations

import json
import math
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, shared_path
from recordings import bag_twin, write_kitti_raw, write_ros1_bag, write_ros2_bag, write_scan_folder
from typer.testing import CliRunner

from cli.main import app
from d3lvo_deploy.datasets import guess_format, open_sequence
from d3lvo_deploy.datasets.kitti_raw import oxts_poses
from d3lvo_deploy.datasets.rosbag import pair_stamps
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.poses import read_poses
from d3lvo_deploy.sequence import KittiSequence

pytest.importorskip("rosbags")
runner = CliRunner()
TINY = ROOT / "tests" / "data" / "tiny_seq"
REAL_FRAMES = 8  # of the 20 real frames, for the format comparisons


def run(*args: str) -> str:
    r = runner.invoke(app, ["run", *args, "--backend", "onnxruntime"])
    assert r.exit_code == 0, r.output
    return r.output


@pytest.fixture(scope="module")
def real_runs(tmp_path_factory):
    """The first eight of the 20 real frames run from KITTI odometry folders: the reference poses,
    for the real calibration and for its bag twin (Tr's rotation through a quaternion, as
    /tf_static holds it). Eight frames: every format's recording holds all twenty, and the poses
    of its first eight are what is compared."""
    seq = KittiSequence.open(shared_path("kitti_raw_snippet", "sequences", "r0926"))
    d = tmp_path_factory.mktemp("real")
    twin = bag_twin(seq, d / "twin")
    poses = {}
    for name, s in (("kitti", seq), ("twin", twin)):
        run(str(s.root), "--out", str(d / f"{name}.txt"), "--end", str(REAL_FRAMES))
        poses[name] = read_poses(d / f"{name}.txt").poses
    return seq, poses


@pytest.mark.parametrize("kind", ["ros2-mcap", "ros1", "ros2-sqlite3-png", "kitti-raw"])
def test_recording_formats_give_the_folder_run_poses(real_runs, tmp_path, kind):
    seq, refs = real_runs
    ref = refs["kitti" if kind == "kitti-raw" else "twin"]
    if kind == "ros2-mcap":
        path = write_ros2_bag(seq, tmp_path / "drive")
    elif kind == "ros1":
        path = write_ros1_bag(seq, tmp_path / "drive.bag")
    elif kind == "ros2-sqlite3-png":
        path = write_ros2_bag(seq, tmp_path / "drive", storage="sqlite3", compressed=True)
    else:
        path = write_kitti_raw(seq, tmp_path / "2011_09_26")
    assert guess_format(path) == ("kitti-raw" if kind == "kitti-raw" else "rosbag")
    out = tmp_path / "poses.txt"
    text = run(str(path), "--out", str(out), "--end", str(REAL_FRAMES))
    poses = read_poses(out).poses
    assert poses.shape == ref.shape
    np.testing.assert_allclose(poses, ref, rtol=0, atol=1e-9)
    assert ("camera frame 'camera'" if kind != "kitti-raw" else "cam0") in text


def test_bag_at_an_mcap_file_and_topic_choice(tmp_path):
    """Two image topics: the error lists both and names the option; the option picks one."""
    seq = KittiSequence.open(TINY)
    bag = write_ros2_bag(seq, tmp_path / "two")
    # a second camera: the same bag's messages under another topic, written again
    from rosbags.rosbag2 import Reader, Writer
    from rosbags.rosbag2 import StoragePlugin

    both = tmp_path / "both"
    with Reader(bag) as r, Writer(both, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for c in r.connections:
            conns[c.topic] = w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest)
        conns["/left/image_raw"] = w.add_connection("/left/image_raw", "sensor_msgs/msg/Image",
                                                    msgdef=next(c for c in r.connections if c.topic ==
                                                                "/camera/image_raw").msgdef.data,
                                                    rihs01=next(c for c in r.connections if c.topic ==
                                                                "/camera/image_raw").digest)
        for c, t, raw in r.messages():
            w.write(conns[c.topic], t, raw)
            if c.topic == "/camera/image_raw":
                w.write(conns["/left/image_raw"], t, raw)
    mcap = next(both.glob("*.mcap"))
    with pytest.raises(D3LVOInputError, match="several image topics: .*/camera/image_raw.*/left/image_raw.*"
                                              "--image-topic"):
        open_sequence(mcap)
    s = open_sequence(mcap, bag=__import__("d3lvo_deploy.datasets", fromlist=["BagOptions"]).BagOptions(
        image_topic="/left/image_raw", info_topic="/camera/camera_info"))
    assert len(s) == 3 and np.array_equal(s.image(2), seq.image(2)) and np.array_equal(s.scan(1), seq.scan(1))


def _zero_rotation(msgs, other_branch: bool) -> None:
    """/tf_static's camera-LiDAR transform with a zero quaternion, or a copy of it on another branch
    of the tree (base_link to imu_link) with one."""
    import copy

    tf = next(m for topic, _, m, _ in msgs if topic == "/tf_static")
    bad = copy.deepcopy(tf.transforms[0]) if other_branch else tf.transforms[0]
    bad.transform.rotation.w = bad.transform.rotation.x = bad.transform.rotation.y = bad.transform.rotation.z = 0.0
    if other_branch:
        bad.header.frame_id, bad.child_frame_id = "base_link", "imu_link"
        tf.transforms = [tf.transforms[0], bad]


def test_a_broken_static_transform_is_set_aside_and_named_where_the_chain_needs_it(tmp_path):
    """A zero quaternion in /tf_static on a branch the run does not need (an IMU's) is set aside: the
    run gives the poses of the intact bag; on the camera-LiDAR transform itself it is one line
    saying which transform was set aside and why (a raw ValueError before)."""
    seq = KittiSequence.open(TINY)
    good = write_ros2_bag(seq, tmp_path / "good")
    other = write_ros2_bag(seq, tmp_path / "other", edit=lambda m: _zero_rotation(m, True))
    for bag in (good, other):
        r = runner.invoke(app, ["run", str(bag), "--method", "direct", "--out", str(tmp_path / f"{bag.name}.txt")])
        assert r.exit_code == 0, r.output
    assert (tmp_path / "other.txt").read_bytes() == (tmp_path / "good.txt").read_bytes()
    chain = write_ros2_bag(seq, tmp_path / "chain", edit=lambda m: _zero_rotation(m, False))
    r = runner.invoke(app, ["run", str(chain), "--method", "direct", "--out", str(tmp_path / "chain.txt")])
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    assert "set aside: a zero-length rotation quaternion" in " ".join(r.output.split()), r.output


@pytest.mark.parametrize("kind, words", [
    ("no-cloud", "has no PointCloud2 topic; its topics: /tf_static"),
    ("no-pairs", "0 of 3 images on /camera/image_raw have a scan on /velodyne_points within 0.05 s (closest: 0.800 s)"),
    ("no-tf", "no LiDAR-camera extrinsics: the bag has no /tf_static; give them with --calib"),
    ("no-info", "no CameraInfo message for /camera/image_raw"),
])
def test_bad_bags_fail_in_one_line_and_write_nothing(tmp_path, monkeypatch, kind, words):
    seq = KittiSequence.open(TINY)
    kw = {"no-cloud": dict(dropped="cloud"), "no-pairs": dict(stamp_offset=1.0), "no-tf": dict(tf=False),
          "no-info": dict(info=False)}[kind]
    bag = write_ros2_bag(seq, tmp_path / "bag", **kw)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    r = runner.invoke(app, ["run", str(bag)])
    assert r.exit_code == 1, r.output
    assert words in r.output and str(bag) in r.output, r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert list(work.iterdir()) == []  # no results folder, no poses


def test_a_calib_file_stands_in_for_missing_extrinsics(tmp_path):
    seq = KittiSequence.open(TINY)
    bag = write_ros2_bag(seq, tmp_path / "bag", tf=False)
    s = open_sequence(bag, calib=TINY / "calib.txt")
    assert np.array_equal(s.calib.Tr, seq.calib.Tr) and np.array_equal(s.calib.P2, seq.calib.P2)


def test_pairing_by_nearest_stamp_by_hand():
    images = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    clouds = np.array([0.38, 0.02, 0.13, 0.29])  # unsorted; none near 0.2 within 0.05
    assert pair_stamps(images, clouds, 0.05) == [(0, 1), (1, 2), (3, 3), (4, 0)]
    assert pair_stamps(images, clouds, 0.011) == [(3, 3)]
    # a camera twice as fast as the LiDAR: each scan keeps the image nearest to it (10 ms), not the
    # first image near it (40 ms)
    assert pair_stamps(np.array([0.0, 0.05, 0.10]), np.array([0.04, 0.14]), 0.05) == [(1, 0), (2, 1)]


@pytest.mark.parametrize("ext", [".pcd", ".ply", ".npy"])
def test_scan_folders_read_the_same_points(tmp_path, ext):
    seq = KittiSequence.open(TINY)
    folder = write_scan_folder(seq, tmp_path / "f", ext)
    assert guess_format(folder) == "folder"
    s = open_sequence(folder)
    for i in range(len(seq)):
        assert np.array_equal(s.scan(i), seq.scan(i))
        assert np.array_equal(s.image(i), seq.image(i))
    np.testing.assert_allclose(s.times, seq.times)


def test_folder_poses_are_in_the_calibrated_camera(tmp_path):
    """K + T_cam_lidar of the colour camera: the same motion as the KITTI run, expressed in that
    camera, i.e. conjugated by cam0 -> cam2, the translation b = K^-1 P2[:, 3] (P2 by hand)."""
    seq = KittiSequence.open(TINY)
    folder = write_scan_folder(seq, tmp_path / "f", ".npy")
    run(str(TINY), "--out", str(tmp_path / "kitti.txt"))
    text = run(str(folder), "--out", str(tmp_path / "cam.txt"))
    assert "the camera of the calibration's K (T_cam_lidar takes the LiDAR there)" in text
    P2 = np.array([float(v) for v in (TINY / "calib.txt").read_text().split("P2:")[1].split("\n")[0].split()]).reshape(3, 4)
    S = np.eye(4)
    S[:3, 3] = np.linalg.solve(P2[:, :3], P2[:, 3])  # x_cam2 = x_cam0 + b
    kitti = read_poses(tmp_path / "kitti.txt").poses
    expected = S @ kitti @ np.linalg.inv(S)
    np.testing.assert_allclose(read_poses(tmp_path / "cam.txt").poses, expected, atol=2e-5)


def test_kitti_raw_oxts_ground_truth_by_hand(tmp_path):
    """Metres per degree at the equator: 2 pi 6378137 / 360 = 111319.49 m. IMU yawing 90 deg on
    the spot with the camera 1 m ahead of it (x): the camera swings to (-1, 1, 0)."""
    deg = 2 * math.pi * 6378137.0 / 360.0
    rec = np.zeros((3, 30))
    rec[1, 1] = 1e-5  # lon: east
    rec[2, 0] = 1e-5  # lat: north
    T = oxts_poses(rec)
    np.testing.assert_allclose(T[1, :3, 3], [1e-5 * deg, 0, 0], atol=1e-6)
    np.testing.assert_allclose(T[2, :3, 3], [0, 1e-5 * deg, 0], atol=1e-6)
    assert np.allclose(T[:, :3, :3], np.eye(3))
    # roll then yaw, 90 deg each: the devkit's R = Rz(yaw) Ry(pitch) Rx(roll), by hand
    rec = np.zeros((2, 30))
    rec[1, 3], rec[1, 5] = math.pi / 2, math.pi / 2
    np.testing.assert_allclose(oxts_poses(rec)[1, :3, :3], [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-12)

    seq = KittiSequence.open(TINY)
    drive = write_kitti_raw(seq, tmp_path / "2011_09_26")
    (drive.parent / "calib_velo_to_cam.txt").write_text("R: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    (drive.parent / "calib_imu_to_velo.txt").write_text("R: 1 0 0 0 1 0 0 0 1\nT: -1 0 0\n")
    (drive / "oxts" / "data").mkdir(parents=True)
    for i, yaw in enumerate([0.0, math.pi / 2, math.pi / 2]):
        row = np.zeros(30)
        row[5] = yaw
        (drive / "oxts" / "data" / f"{i:010d}.txt").write_text(" ".join(map(str, row)))
    gt = open_sequence(drive).ground_truth.poses
    np.testing.assert_allclose(gt[1, :3, 3], [-1, 1, 0], atol=1e-9)
    np.testing.assert_allclose(gt[1, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-9)


def test_unknown_recording_names_the_formats(tmp_path):
    (tmp_path / "x").mkdir()
    r = runner.invoke(app, ["run", str(tmp_path / "x")])
    assert r.exit_code == 1 and "is none of the formats D3LVO reads" in r.output and "--format" in r.output


def test_results_folder_holds_the_run_and_its_config_repeats_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    text = run(str(TINY))
    first = Path("results/latest").resolve()
    assert first.parent == (tmp_path / "results").resolve() and first.name.startswith("tiny_seq_")
    for name in ("poses.txt", "poses_tum.txt", "config.toml", "metrics.json", "latency.json"):
        assert (first / name).is_file(), (name, text)
    poses = read_poses(first / "poses.txt").poses
    tum = read_poses(first / "poses_tum.txt", fmt="tum")
    np.testing.assert_allclose(tum.poses, poses, atol=1e-9)
    np.testing.assert_allclose(tum.timestamps, KittiSequence.open(TINY).times)
    # ATE without alignment, by hand: RMSE of the position differences against poses.txt beside tiny_seq
    gt = read_poses(TINY / "poses.txt").poses
    gt = np.linalg.inv(gt[0]) @ gt
    ate = np.sqrt(np.mean(np.sum((gt[:, :3, 3] - poses[:, :3, 3]) ** 2, 1)))
    assert json.loads((first / "metrics.json").read_text())["ate"] == pytest.approx(ate, rel=1e-9)
    lat = json.loads((first / "latency.json").read_text())
    assert lat["frames"] == 3 and len(lat["per_frame_total"]) == 3
    cfg = (first / "config.toml").read_text()
    assert 'backend = "onnxruntime"' in cfg and "manifest_sha256" in cfg and "cpu = " in cfg
    machine = tomllib.loads(cfg)["machine"]  # the threads the run's stages and its frames' preparation took
    assert machine["pipeline_depth"] == 1 and machine["prepare_threads"] in (1, 2)

    r = runner.invoke(app, ["run", "--config", str(first / "config.toml")])
    assert r.exit_code == 0, r.output
    second = Path("results/latest").resolve()
    assert second != first
    assert (second / "poses.txt").read_bytes() == (first / "poses.txt").read_bytes()
    # an option given on the command line wins over the file's (start = 0 there)
    r = runner.invoke(app, ["run", "--config", str(first / "config.toml"), "--start", "1"])
    assert r.exit_code == 0, r.output
    assert len(read_poses(Path("results/latest/poses.txt"))) == 2

    bad = tmp_path / "bad.toml"
    bad.write_text("[run]\nbackend = 'onnxruntime'\nspeed = 3\n")
    r = runner.invoke(app, ["run", "--config", str(bad)])
    assert r.exit_code == 1 and "unknown option 'speed'" in r.output and str(bad) in r.output


def test_run_records_the_classical_solve_beside_and_repeats_the_switch(tmp_path, monkeypatch):
    """On two threads the bundled model's classical solve runs beside completion and encoder: the
    model line says so and config.toml records it with each stage's threads; --no-classical-beside
    runs the one-graph solve, is recorded in [run] and repeated by --config, with the same poses."""
    monkeypatch.chdir(tmp_path)
    runs = {}
    for flag in ("--classical-beside", "--no-classical-beside"):
        r = runner.invoke(app, ["run", str(TINY), "--backend", "onnxruntime", "--threads", "2", flag])
        assert r.exit_code == 0, r.output
        folder = Path("results/latest").resolve()
        cfg = tomllib.loads((folder / "config.toml").read_text())
        runs[flag] = folder, cfg
        beside = flag == "--classical-beside"
        assert cfg["run"]["classical_beside"] is beside and cfg["machine"]["classical_beside"] is beside
        assert ("classical solve on a second thread" in r.output) is beside
    machine = runs["--classical-beside"][1]["machine"]
    assert machine["classical_threads"] == 1 and machine["encoder_threads"] == 1 and machine["flowpose_threads"] == 2
    assert "classical_threads" not in runs["--no-classical-beside"][1]["machine"]
    r = runner.invoke(app, ["run", "--config", str(runs["--no-classical-beside"][0] / "config.toml")])
    assert r.exit_code == 0 and "classical solve on a second thread" not in r.output, r.output
    repeat = Path("results/latest").resolve()
    assert tomllib.loads((repeat / "config.toml").read_text())["machine"]["classical_beside"] is False
    poses = [(f / "poses.txt").read_bytes() for f in (runs["--classical-beside"][0], runs["--no-classical-beside"][0], repeat)]
    assert poses[0] == poses[1] == poses[2]


def test_resume_needs_the_folder_it_continues(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = runner.invoke(app, ["run", str(TINY), "--resume"])
    assert r.exit_code == 1 and "--resume continues a results folder: name it with --out-dir" in r.output
    out = tmp_path / "res"
    run(str(TINY), "--out-dir", str(out), "--end", "2")
    run(str(TINY), "--out-dir", str(out), "--resume")
    whole = tmp_path / "whole"
    run(str(TINY), "--out-dir", str(whole))
    assert (out / "poses.txt").read_text() == (whole / "poses.txt").read_text()


def test_kitti_format_without_a_scan_folder_is_one_error(tmp_path):
    shutil.copytree(TINY, tmp_path / "s")
    shutil.rmtree(tmp_path / "s" / "velodyne")
    r = runner.invoke(app, ["run", str(tmp_path / "s"), "--format", "kitti"])
    assert r.exit_code == 1 and "velodyne" in r.output and "missing" in r.output


def test_format_names_are_case_blind_and_a_plot_elsewhere_is_named_by_its_path(tmp_path):
    """--format KITTI is kitti (as --pose-format TUM is tum); a --plot outside the results folder
    is listed with its path, not as if the folder held it."""
    pytest.importorskip("matplotlib")
    r = runner.invoke(app, ["run", str(TINY), "--format", "KITTI", "--backend", "onnxruntime",
                            "--out-dir", str(tmp_path / "r"), "--plot", str(tmp_path / "top.png")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "top.png").is_file() and not (tmp_path / "r" / "top.png").exists()
    listed = r.output.split("results in", 1)[1].replace("\n", "")
    assert str(tmp_path / "top.png") in listed and ", top.png" not in listed, r.output


def test_runs_started_together_get_their_own_folders_and_a_refused_run_none(tmp_path, monkeypatch):
    from d3lvo_deploy.results import default_folder

    now = 1_700_000_000.0
    a, b = default_folder(tmp_path / "results", "drive", now), default_folder(tmp_path / "results", "drive", now)
    assert a != b and a.is_dir() and b.is_dir() and b.name == a.name + "-2"
    monkeypatch.chdir(tmp_path)
    r = runner.invoke(app, ["run", str(TINY), "--onnx", str(tmp_path / "nowhere")])
    assert r.exit_code == 1
    assert sorted(p.name for p in (tmp_path / "results").iterdir()) == sorted([a.name, b.name])  # none added


def test_resume_continues_only_the_run_its_config_records(tmp_path, monkeypatch):
    """--resume appends to the poses of the same recording, start and model only: another
    recording or start is one error naming the option and both values, and nothing is added; the
    config written beside an --out trajectory is what it checks, and what --config repeats."""
    monkeypatch.chdir(tmp_path)
    other = tmp_path / "other"
    shutil.copytree(TINY, other)
    out = tmp_path / "res"
    run(str(TINY), "--out-dir", str(out), "--end", "2")
    saved = [(out / n).read_bytes() for n in ("poses.txt", "config.toml")]
    r = runner.invoke(app, ["run", str(other), "--out-dir", str(out), "--resume", "--backend", "onnxruntime"])
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    for words in (f"the poses in {out / 'poses.txt'} are of a run with path = '{TINY.resolve()}'",
                  f"this one has '{other.resolve()}'", "--overwrite"):
        assert words in r.output, r.output
    assert [(out / n).read_bytes() for n in ("poses.txt", "config.toml")] == saved

    p = tmp_path / "p.txt"
    run(str(TINY), "--out", str(p), "--end", "2")
    record = tmp_path / "p.txt.config.toml"
    assert tomllib.loads(record.read_text())["run"]["end"] == 2
    r = runner.invoke(app, ["run", str(TINY), "--out", str(p), "--resume", "--start", "1", "--backend", "onnxruntime"])
    assert r.exit_code == 1 and "are of a run with start = 0, this one has 1" in r.output, r.output
    assert len(p.read_text().splitlines()) == 2
    run(str(TINY), "--out", str(p), "--resume")
    r = runner.invoke(app, ["run", "--config", str(record), "--out", str(tmp_path / "q.txt")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "q.txt").read_bytes() == p.read_bytes() and len(p.read_text().splitlines()) == 3
    record.unlink()
    r = runner.invoke(app, ["run", str(TINY), "--out", str(p), "--resume", "--backend", "onnxruntime"])
    assert r.exit_code == 0 and "missing, so nothing shows that the poses in" in r.output, r.output


@pytest.mark.parametrize("extra, words", [
    (["--out", "p.txt", "--out-dir", "d"], "--out writes one trajectory file and --out-dir a results folder"),
    (["--out", "p.txt", "--resume", "--overwrite"], "--resume continues the poses already written and --overwrite"),
    (["--pose-format", "tum"], "--pose-format tum is for --out FILE; a results folder holds both"),
    (["--out", "p.txt", "--image-topic", "/cam", "--max-dt", "0.1"],
     "--image-topic, --max-dt are for ROS bags; this is a kitti recording"),
    (["--out", "p.txt", "--gt", "nowhere.txt"], "nowhere.txt: pose file not found"),
    (["--out", "p.txt", "--max-dt", "-1"], "--max-dt must be a time of 0 s or more"),
    (["--out", "p.txt", "--gt", str(ROOT / "tests" / "data")], "data: is a folder; a pose file was expected"),
    (["--out", "p.txt", "--gt", str(ROOT / "tests" / "data" / "tiny_seq" / "times.txt")],
     "1 columns per line: expected 12 (KITTI)"),
])
def test_options_that_cannot_work_together_or_score_stop_before_any_frame(tmp_path, monkeypatch, extra, words):
    monkeypatch.chdir(tmp_path)
    r = runner.invoke(app, ["run", str(TINY), "--backend", "onnxruntime", *extra])
    assert r.exit_code == 1 and words in r.output and "Traceback" not in r.output, r.output
    assert list(tmp_path.iterdir()) == []  # no trajectory, no folder


def test_ground_truth_of_another_length_stops_before_the_first_frame(tmp_path):
    """Named with --gt: an error before any frame. Found beside the frames (a full drive's poses.txt
    beside some of its frames): a warning, and the run goes on unscored."""
    gt = tmp_path / "gt.txt"
    gt.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5)
    r = runner.invoke(app, ["run", str(TINY), "--gt", str(gt), "--out", str(tmp_path / "p.txt")])
    assert r.exit_code == 1 and "5 poses for a sequence of 3 frames" in r.output, r.output
    assert not (tmp_path / "p.txt").exists()
    shutil.copytree(TINY, tmp_path / "s")
    shutil.copy(gt, tmp_path / "s" / "poses.txt")
    r = runner.invoke(app, ["run", str(tmp_path / "s"), "--out", str(tmp_path / "p.txt"), "--backend", "onnxruntime"])
    assert r.exit_code == 0 and "the run goes on without scoring" in r.output and "no metrics" in r.output, r.output
    assert len((tmp_path / "p.txt").read_text().splitlines()) == 3


@pytest.mark.parametrize("line, words", [('threads = "two"', "[run] threads = 'two': expected a whole number"),
                                         ("start = 1.5", "[run] start = 1.5: expected a whole number"),
                                         ("path = 3", "[run] path = 3: expected a quoted string (a path)"),
                                         ('pipeline = "yes"', "[run] pipeline = 'yes': expected true or false")])
def test_a_config_value_of_the_wrong_type_names_its_key(tmp_path, line, words):
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[run]\n{line}\n" if line.startswith("path") else f'[run]\npath = "{TINY}"\n{line}\n')
    r = runner.invoke(app, ["run", "--config", str(cfg), "--out", str(tmp_path / "p.txt")])
    assert r.exit_code == 1 and words in r.output and str(cfg) in r.output and "Traceback" not in r.output, r.output


@pytest.mark.parametrize("value, like, ok", [
    (True, bool, True), (1, bool, False), (3, 0, True), (3.0, 0, False), (True, 0, False),
    (3, 0.5, True), (float("nan"), 0.5, False), (float("inf"), float, False), ("x", Path, True), (3, Path, False),
    ([16, 32], (8, 16), True), ([1.5], (8,), False), ([1, 2.5], (0.5,), True), (["a"], [], True), ([1], [], False)])
def test_config_values_fit_the_kind_of_their_default(value, like, ok):
    """One rule for `run --config`, training configs and `--set`: the default's kind, numbers
    finite, ints standing for floats but not the other way round, list elements like the
    default's first (strings where it is empty)."""
    from d3lvo_deploy.config_values import converted, fits

    assert fits(value, like) is ok
    if ok and isinstance(like, tuple):
        assert converted(value, like) == tuple(value)
    if ok and like == 0.5:
        assert type(converted(value, like)) is float


def test_empty_kitti_folders_say_what_is_missing(tmp_path):
    for d in ("image_2", "velodyne"):
        (tmp_path / "s" / d).mkdir(parents=True)
    r = runner.invoke(app, ["run", str(tmp_path / "s")])
    assert r.exit_code == 1 and "image_2: holds no .png images" in r.output, r.output


def test_scan_warnings_name_their_frame(tmp_path):
    from cli.run_cmd import SCAN_WARNINGS_SHOWN, _print_warnings
    from d3lvo_deploy.odometry import ScanWarning

    shutil.copytree(TINY, tmp_path / "s")
    (tmp_path / "s" / "velodyne" / "000001.bin").write_bytes(b"")
    r = runner.invoke(app, ["run", str(tmp_path / "s"), "--out", str(tmp_path / "p.txt"), "--backend", "onnxruntime"])
    assert r.exit_code == 0 and "frame 000001's scan: no LiDAR points" in r.output, r.output
    assert len((tmp_path / "p.txt").read_text().splitlines()) == 3

    class W:  # what warnings.catch_warnings records
        def __init__(self, k):
            self.message, self.category = f"frame {k:06d}'s scan: no LiDAR points", ScanWarning

    from cli.common import console

    shown: set[str] = set()
    with console.capture() as cap:
        _print_warnings([W(k) for k in range(SCAN_WARNINGS_SHOWN + 2)], shown)
    lines = cap.get().splitlines()
    assert len(lines) == SCAN_WARNINGS_SHOWN + 1 and lines[0].endswith("frame 000000's scan: no LiDAR points")
    assert "and 2 more scan warnings, one per frame, not shown" in lines[-1]
    with console.capture() as cap:  # a later step of the same command: what was printed is not again
        _print_warnings([W(0), W(SCAN_WARNINGS_SHOWN + 5)], shown)
    lines = cap.get().splitlines()
    assert len(lines) == 1 and lines[0].endswith(f"frame {SCAN_WARNINGS_SHOWN + 5:06d}'s scan: no LiDAR points")


def test_a_pcd_that_cannot_be_read_is_one_line(tmp_path):
    """The PCD reader's own report (a validator's, many lines) is cut to its first line."""
    pytest.importorskip("pypcd4")
    folder = write_scan_folder(KittiSequence.open(TINY), tmp_path / "f", ".pcd")
    bad = sorted((folder / "scans").glob("*.pcd"))[1]
    bad.write_text("garbage\n")
    r = runner.invoke(app, ["run", str(folder), "--out", str(tmp_path / "p.txt"), "--method", "direct"])
    assert r.exit_code == 1 and f"{bad.name}: cannot be read as a PCD file (" in r.output, r.output
    error = [line for line in r.output.splitlines() if "error" in line]
    assert len(error) == 1 and "--resume" in r.output and "errors.pydantic" not in r.output, r.output


def test_a_scan_that_is_not_npy_names_the_file(tmp_path):
    folder = write_scan_folder(KittiSequence.open(TINY), tmp_path / "f", ".npy")
    bad = sorted((folder / "scans").glob("*.npy"))[1]
    bad.write_bytes(b"garbage")
    r = runner.invoke(app, ["run", str(folder), "--out", str(tmp_path / "p.txt"), "--backend", "onnxruntime"])
    assert r.exit_code == 1 and f"{bad.name}: is not a .npy file (no NumPy header" in r.output, r.output


def test_a_config_repeated_on_another_recording_leaves_the_old_ones_topics(tmp_path):
    """A bag run's config names its topics; repeated on another recording (PATH given), those stay
    with the bag; repeated on its own recording, they are its options, and a KITTI folder refuses them."""
    shutil.copytree(TINY, tmp_path / "other")
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[run]\npath = "{TINY}"\nimage_topic = "/cam"\nmax_dt = 0.1\nbackend = "onnxruntime"\n')
    r = runner.invoke(app, ["run", str(tmp_path / "other"), "--config", str(cfg), "--out", str(tmp_path / "p.txt")])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["run", "--config", str(cfg), "--out", str(tmp_path / "q.txt")])
    assert r.exit_code == 1 and "--image-topic, --max-dt are for ROS bags" in r.output, r.output


def test_folder_frames_run_in_number_order_and_a_gap_stops(tmp_path):
    """frame_8, frame_9, frame_10 (unpadded) run in that order, not as text sorts them (frame_10
    first); a missing frame_9 is a gap, as in a KITTI folder."""
    seq = KittiSequence.open(TINY)
    folder = write_scan_folder(seq, tmp_path / "f", ".npy")
    for sub, ext in (("images", ".png"), ("scans", ".npy")):
        for i in range(3):
            (folder / sub / f"{i:06d}{ext}").rename(folder / sub / f"frame_{8 + i}{ext}")
    s = open_sequence(folder)
    assert s.frame_names == ["frame_8", "frame_9", "frame_10"]
    assert all(np.array_equal(s.scan(i), seq.scan(i)) for i in range(3))
    for sub, ext in (("images", ".png"), ("scans", ".npy")):
        (folder / sub / f"frame_9{ext}").rename(folder / sub / f"frame_11{ext}")
    (folder / "times.txt").unlink()
    with pytest.raises(D3LVOInputError, match="frame numbers jump from frame_8 to frame_10"):
        open_sequence(folder)
    # names that count milliseconds, or decimal time stamps, are no frame counts: text order, no gap check
    for sub, ext in (("images", ".png"), ("scans", ".npy")):
        for k, stem in enumerate(("frame_8", "frame_10", "frame_11")):
            (folder / sub / f"{stem}{ext}").rename(folder / sub / f"1630000000.{('05', '1', '15')[k]}{ext}")
    assert open_sequence(folder).frame_names == ["1630000000.05", "1630000000.1", "1630000000.15"]


def test_a_folder_ground_truth_that_does_not_fit_is_a_warning(tmp_path):
    """As for a KITTI folder: a poses.txt found beside the frames that does not fit leaves the run
    unscored, with a warning; named with --gt it stops the run."""
    seq = KittiSequence.open(TINY)
    folder = write_scan_folder(seq, tmp_path / "f", ".npy")
    (folder / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
    r = runner.invoke(app, ["run", str(folder), "--out", str(tmp_path / "p.txt"), "--backend", "onnxruntime"])
    assert r.exit_code == 0 and "2 poses for a sequence of 3 frames" in r.output and "without scoring" in r.output, \
        r.output
    r = runner.invoke(app, ["run", str(folder), "--out", str(tmp_path / "q.txt"), "--gt", str(folder / "poses.txt")])
    assert r.exit_code == 1 and "2 poses for a sequence of 3 frames" in r.output, r.output


def test_kitti_raw_gaps_and_missing_scans_are_named(tmp_path):
    seq = KittiSequence.open(TINY)
    drive = write_kitti_raw(seq, tmp_path / "2011_09_26")
    (drive / "velodyne_points" / "data" / "0000000002.bin").unlink()
    with pytest.raises(D3LVOInputError, match=r"frames without a scan: \['0000000002'\]"):
        open_sequence(drive)
    (drive / "image_02" / "data" / "0000000002.png").unlink()
    (drive / "image_02" / "data" / "0000000001.png").rename(drive / "image_02" / "data" / "0000000002.png")
    (drive / "velodyne_points" / "data" / "0000000001.bin").rename(drive / "velodyne_points" / "data" / "0000000002.bin")
    (drive / "image_02" / "timestamps.txt").unlink()
    with pytest.raises(D3LVOInputError, match="frame numbers jump from 0000000000 to 0000000002"):
        open_sequence(drive)


def test_bag_camera_info_of_another_size_and_beside_a_compressed_topic(tmp_path):
    """A CameraInfo for another resolution is one error at the first image, not intrinsics
    silently misapplied; the CameraInfo beside /camera/image_raw/compressed is /camera/camera_info
    even with another camera's CameraInfo in the bag."""
    seq = KittiSequence.open(TINY)
    big = write_ros2_bag(seq, tmp_path / "big", info_size=(1242, 376))
    with pytest.raises(D3LVOInputError, match="the CameraInfo gives 1242x376 images, but frame 0's image"):
        open_sequence(big).image(0)
    two = write_ros2_bag(seq, tmp_path / "two", compressed=True, second_info=True)
    s = open_sequence(two)
    assert np.array_equal(s.calib.P2, seq.calib.P2) and np.array_equal(s.image(1), seq.image(1))


def test_input_errors_cross_process_boundaries_whole():
    """A scale-out worker's error reaches the parent pickled: the same path and problem, one line."""
    import pickle

    e = pickle.loads(pickle.dumps(D3LVOInputError(Path("a/b.bin"), "100 bytes is not a whole number of points")))
    assert isinstance(e, D3LVOInputError) and e.path == Path("a/b.bin") and str(e) == "a/b.bin: 100 bytes is not a " \
        "whole number of points"


def test_eval_of_folders_scores_what_has_ground_truth(tmp_path):
    """Estimates of sequences without ground truth (KITTI 11-21) are left out with a note; the
    others are scored as alone."""
    gt, est = tmp_path / "gt", tmp_path / "est"
    gt.mkdir()
    est.mkdir()
    poses = "".join(f"1 0 0 0 0 1 0 0 0 0 1 {0.8 * k}\n" for k in range(12))
    (gt / "00.txt").write_text(poses)
    (est / "00.txt").write_text(poses)
    (est / "11.txt").write_text(poses)
    r = runner.invoke(app, ["eval", "--gt", str(gt), "--est", str(est), "--json"])
    assert r.exit_code == 0, r.output
    assert "11.txt not scored" in r.output
    (gt / "00.txt").rename(gt / "01.txt")
    r = runner.invoke(app, ["eval", "--gt", str(gt), "--est", str(est)])
    assert r.exit_code == 1 and "holds no ground truth of the names" in r.output, r.output


def test_api_inputs_the_cli_checks_are_checked_from_python_too(tmp_path):
    """What a Python caller passes where the CLI would have converted or refused it: paths as
    strings, a picture interval of 0, pose arrays for scoring, (N,3,4) KITTI-shaped poses, a path
    that is no bag under --format rosbag, and the direct tracker's calibration and poses."""
    from d3lvo_deploy.direct import DirectOdometry
    from d3lvo_deploy.evaluation import evaluate
    from d3lvo_deploy.pipeline import RunConfig, run_sequence
    from d3lvo_deploy.poses import Trajectory

    seq = KittiSequence.open(TINY)
    gt = seq.ground_truth.poses
    assert evaluate(gt, gt[:, :3]).ate == 0.0  # arrays, KITTI's (N,3,4) too, read as the same poses
    with pytest.raises(D3LVOInputError, match=r"poses must be \(N,4,4\) or \(N,3,4\), got shape \(9, 4\)"):
        Trajectory.from_poses(gt[:, :3].reshape(-1, 4))
    with pytest.raises(D3LVOInputError, match="viz_every must be a whole number of frames, 1 or more"):
        run_sequence(seq, None, RunConfig(out=str(tmp_path / "p.txt"), viz_dir=str(tmp_path / "v"), viz_every=0))
    assert not (tmp_path / "p.txt").exists()
    s = run_sequence(seq, None, RunConfig(out=str(tmp_path / "p.txt"), viz_dir=str(tmp_path / "v"), viz_every=1),
                     odometry=None)
    assert s is not None and len(list((tmp_path / "v").glob("*.png"))) == 2  # the bundled model, strings as paths
    with pytest.raises(D3LVOInputError, match="cannot be read as a ROS 1 / ROS 2 bag"):
        open_sequence(TINY, fmt="rosbag")
    direct = DirectOdometry(str(TINY / "calib.txt"))  # a path, as Odometry takes it
    poses = [direct.step(seq.image(i), seq.scan(i)) for i in range(3)]
    np.testing.assert_allclose(poses[2], poses[1] @ direct.relative, atol=1e-12)
    # in cam0: the image_2 motion the solver tracked, moved through the rig (b = K2^-1 P2[:, 3])
    S = np.eye(4)
    S[:3, 3] = -np.linalg.solve(seq.calib.P2[:, :3], seq.calib.P2[:, 3])
    np.testing.assert_allclose(direct.relative, S @ direct.motion2 @ np.linalg.inv(S), atol=1e-12)
    direct.prime(seq.image(1), seq.scan(1), poses[1], previous_pose=poses[0])
    np.testing.assert_allclose(direct.relative, np.linalg.inv(poses[0]) @ poses[1], atol=1e-12)
    with pytest.raises(D3LVOInputError, match="start_pose must be a 4x4"):
        direct.reset(np.eye(3))
    mm = seq.scan(0).copy()
    mm[:, :3] *= 1000.0
    with pytest.raises(D3LVOInputError, match="must be in metres"):
        DirectOdometry(seq.calib).step(seq.image(0), mm)


def test_brackets_in_paths_are_printed_as_they_are(small_synth, tmp_path):
    """Folder names with brackets (`res[v2]`, `[/]`, rich's markup syntax) are named as typed, and
    a run into one writes every result: read as markup, `res[v2]` would print as `res`, and `[/]`
    would stop the run with a markup error after the poses, before the metrics."""
    for name in ("res[v2]", "r[/]x", "[bold]b", "e:cat:x"):  # and no emoji code read into a name
        folder = tmp_path / name
        r = runner.invoke(app, ["run", str(small_synth), "--method", "direct", "--out-dir", str(folder)])
        assert r.exit_code == 0, r.output
        assert f"results in {folder}: poses.txt" in r.output, r.output
        assert (folder / "metrics.json").is_file() and (folder / "trajectory.png").is_file()
    r = runner.invoke(app, ["run", str(small_synth), "--method", "direct", "--out", str(tmp_path / "[x]" / "p.txt")])
    assert r.exit_code == 0 and f"in {tmp_path / '[x]' / 'p.txt'}" in r.output, r.output


def test_a_config_repeated_on_another_recording_scores_it_against_its_own_ground_truth(tmp_path):
    """The config's `gt` and `calib` belong to its recording: repeated on another one, the run is
    scored against the other's own poses.txt (as `d3lvo eval` scores it), not the old ground truth;
    an overwritten results folder keeps no earlier run's scores where this run has none."""
    shutil.copytree(TINY, tmp_path / "other")
    poses = read_poses(TINY / "poses.txt").poses.copy()
    poses[:, :3, 3] *= 3.0  # a ground truth of some other drive
    np.savetxt(tmp_path / "wrong_gt.txt", poses[:, :3].reshape(len(poses), 12))
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[run]\npath = "{TINY}"\nmethod = "direct"\ngt = "{tmp_path / "wrong_gt.txt"}"\n')
    r = runner.invoke(app, ["run", str(tmp_path / "other"), "--config", str(cfg), "--out-dir", str(tmp_path / "r")])
    assert r.exit_code == 0, r.output
    e = runner.invoke(app, ["eval", "--gt", str(tmp_path / "other" / "poses.txt"), "--est", str(tmp_path / "r" / "poses.txt"),
                            "--json"])
    want = json.loads(e.stdout)["ate"]
    assert json.loads((tmp_path / "r" / "metrics.json").read_text())["ate"] == pytest.approx(want, abs=1e-9)
    # the config's own recording named on the command line keeps the config's ground truth
    r = runner.invoke(app, ["run", str(TINY), "--config", str(cfg), "--out-dir", str(tmp_path / "own")])
    assert r.exit_code == 0, r.output
    e = runner.invoke(app, ["eval", "--gt", str(tmp_path / "wrong_gt.txt"), "--est", str(tmp_path / "own" / "poses.txt"),
                            "--json"])
    assert json.loads((tmp_path / "own" / "metrics.json").read_text())["ate"] == pytest.approx(
        json.loads(e.stdout)["ate"], abs=1e-9)
    (tmp_path / "other" / "poses.txt").unlink()
    r = runner.invoke(app, ["run", str(tmp_path / "other"), "--method", "direct", "--out-dir", str(tmp_path / "r"),
                            "--overwrite"])
    assert r.exit_code == 0 and "no metrics" in r.output, r.output
    assert not (tmp_path / "r" / "metrics.json").exists()


def test_a_config_file_that_is_not_utf8_or_has_a_non_table_model_is_one_line(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_bytes(f'# mod\xe8le\n[run]\npath = "{TINY}"\n'.encode("latin-1"))
    r = runner.invoke(app, ["run", "--config", str(cfg), "--method", "direct", "--out", str(tmp_path / "p.txt")])
    assert r.exit_code == 1 and "is not UTF-8 text" in r.output and "Traceback" not in r.output, r.output
    cfg.write_text(f'model = "x"\n[run]\npath = "{TINY}"\nmethod = "direct"\n')  # no [model] table: nothing to check
    r = runner.invoke(app, ["run", "--config", str(cfg), "--out", str(tmp_path / "p.txt")])
    assert r.exit_code == 0, r.output


def test_more_threads_than_cores_is_noted(tmp_path):
    import os

    many = (os.cpu_count() or 1) + 1
    r = runner.invoke(app, ["run", str(TINY), "--method", "direct", "--out", str(tmp_path / "p.txt"), "--threads", str(many)])
    assert r.exit_code == 0 and f"--threads {many} is more than the" in r.output and "cores this process" in r.output, \
        r.output
    r = runner.invoke(app, ["run", str(TINY), "--method", "direct", "--out", str(tmp_path / "q.txt"), "--threads", "1"])
    assert r.exit_code == 0 and "cores this process" not in r.output, r.output


def test_a_latest_folder_of_the_users_is_left_as_it_is(tmp_path, monkeypatch):
    """`results/latest` is the link to the newest run; where it is a folder of the user's, a run
    leaves it (and no stray link beside it) and says so."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "results" / "latest").mkdir(parents=True)
    (tmp_path / "results" / "latest" / "mine.txt").write_text("mine")
    r = runner.invoke(app, ["run", str(TINY), "--method", "direct"])
    assert r.exit_code == 0 and "is not the link d3lvo keeps to the newest run" in r.output, r.output
    assert (tmp_path / "results" / "latest" / "mine.txt").read_text() == "mine"
    assert not [p for p in (tmp_path / "results").iterdir() if p.name.startswith(".latest")]
    r = runner.invoke(app, ["run", str(TINY), "--method", "direct", "--out-dir", str(tmp_path / "results" / "x")])
    assert r.exit_code == 0 and "not the link" not in r.output  # --out-dir: no link, no note
