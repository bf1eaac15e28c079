"""Many sequences on workers: chunking, stitching, and equality with the sequential run."""

import re
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from cli.main import app
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.geometry import axis_angle_to_rot, make_se3
from d3lvo_deploy.pipeline import RunConfig, run_sequence
from d3lvo_deploy.poses import read_poses
from d3lvo_deploy.scaleout import parse_sequences, plan_chunks, run_many, stitch
from d3lvo_deploy.sequence import KittiSequence
from d3lvo_deploy.synth.generator import SynthConfig, generate

runner = CliRunner()


def test_plan_chunks_by_hand():
    assert plan_chunks(10, 4, 1) == [(0, 4), (3, 7), (6, 10)]
    assert plan_chunks(4, 4, 1) == [(0, 4)]
    assert plan_chunks(11, 5, 2) == [(0, 5), (3, 8), (6, 11)]
    assert parse_sequences("00-02,05") == ["00", "01", "02", "05"]


@pytest.mark.parametrize("spec, words", [("10-00", "runs backwards (write 00-10)"), (",", "names no sequence"),
                                         ("0a", "must look like 00-10")])
def test_a_sequence_list_that_names_nothing_is_refused(spec, words):
    with pytest.raises(D3LVOInputError, match=re.escape(words)):
        parse_sequences(spec)


def test_stitch_recovers_a_trajectory():
    rng = np.random.default_rng(0)
    rel = [make_se3(axis_angle_to_rot(rng.normal(size=3) * 0.05), rng.normal(size=3)) for _ in range(9)]
    full = [np.eye(4)]
    for A in rel:
        full.append(full[-1] @ A)
    full = np.array(full)
    parts = []
    for s, e in plan_chunks(10, 4, 2):
        parts.append((s, np.linalg.inv(full[s]) @ full[s:e]))
    traj, residual = stitch(parts)
    np.testing.assert_allclose(traj, full, atol=1e-9)
    assert residual < 1e-9


@pytest.fixture(scope="module")
def kitti_root(small_synth, tmp_path_factory):
    root = tmp_path_factory.mktemp("kitti")
    shutil.copytree(small_synth, root / "sequences" / "00")
    generate(root / "sequences" / "01", SynthConfig(frames=5, seed=8, width=620, height=188))
    (root / "poses").mkdir()
    for s in ("00", "01"):
        shutil.move(root / "sequences" / s / "poses.txt", root / "poses" / f"{s}.txt")
    return root


def _sequential(kitti_root, onnx_dir, tmp_path):
    out = {}
    for s in ("00", "01"):
        run_sequence(KittiSequence.from_kitti_root(kitti_root, s), onnx_dir, RunConfig(out=tmp_path / f"seq_{s}.txt"))
        out[s] = read_poses(tmp_path / f"seq_{s}.txt").poses
    return out


@pytest.fixture(scope="module")
def chunked_reference(kitti_root, small_model, tmp_path_factory):
    """The sequential engine's stitched trajectories, and one uninterrupted run per sequence."""
    _, onnx_dir = small_model
    tmp = tmp_path_factory.mktemp("ref")
    dirs = {s: kitti_root / "sequences" / s for s in ("00", "01")}
    res = run_many(dirs, onnx_dir, tmp / "out", engine="sequential", workers=1, chunk=4, overlap=2)
    got = {s: read_poses(tmp / "out" / f"{s}.txt").poses for s in dirs}
    return got, res, _sequential(kitti_root, onnx_dir, tmp)


def test_chunked_run_is_close_to_the_uninterrupted_one(chunked_reference):
    """Each chunk's first pair starts the Gauss-Newton head from rest; the stitch anchors past it.
    With this untrained test model the solver is far from converged, so a cold start moves the
    pose by about a millimetre (the trained bundled model: see README, scale-out)."""
    got, res, ref = chunked_reference
    for s in ("00", "01"):
        assert got[s].shape == ref[s].shape
        np.testing.assert_allclose(got[s][0], np.eye(4), atol=1e-12)
        np.testing.assert_allclose(got[s], ref[s], atol=1e-2)
        assert res[s] < 1e-2


@pytest.mark.parametrize("engine", ["local", "ray"])
def test_engines_equal_the_sequential_engine(kitti_root, small_model, chunked_reference, tmp_path, engine):
    """Same chunks, same sessions: parallel engines give exactly the sequential engine's poses."""
    if engine == "ray":
        ray = pytest.importorskip("ray", reason="Ray is the optional [ray] extra")
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)  # local, loopback only
    _, onnx_dir = small_model
    try:
        dirs = {s: kitti_root / "sequences" / s for s in ("00", "01")}
        res = run_many(dirs, onnx_dir, tmp_path / "out", engine=engine, workers=2, chunk=4, overlap=2)
    finally:
        if engine == "ray":
            ray.shutdown()
    ref, ref_res, _ = chunked_reference
    for s in ("00", "01"):
        np.testing.assert_allclose(read_poses(tmp_path / "out" / f"{s}.txt").poses, ref[s], atol=1e-7)
        assert res[s] == pytest.approx(ref_res[s], abs=1e-7)


def test_cli_many_sequences_with_eval(kitti_root, small_model, tmp_path):
    _, onnx_dir = small_model
    r = runner.invoke(app, ["run", "--kitti-root", str(kitti_root), "--sequences", "00-01", "--out-dir", str(tmp_path / "o"),
                            "--onnx", str(onnx_dir), "--engine", "sequential", "--chunk", "4"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "o" / "00.txt").is_file() and (tmp_path / "o" / "01.txt").is_file()
    assert "all" in r.output  # the devkit-style aggregate row of `d3lvo eval`
    r = runner.invoke(app, ["run", "--kitti-root", str(kitti_root), "--sequences", "00-03", "--out-dir", str(tmp_path / "o"),
                            "--onnx", str(onnx_dir)])
    assert r.exit_code == 1 and "sequence 02 not found" in r.output
    # the same folder again: its poses are not replaced unless asked (--overwrite), as a single run's
    before = (tmp_path / "o" / "00.txt").read_bytes()
    again = ["run", "--kitti-root", str(kitti_root), "--sequences", "00-01", "--out-dir", str(tmp_path / "o"),
             "--onnx", str(onnx_dir), "--engine", "sequential", "--chunk", "4", "--max-accel", "0.001"]
    r = runner.invoke(app, again)
    assert r.exit_code == 1 and "00.txt: already holds poses from an earlier run (2 of the 2" in r.output, r.output
    assert (tmp_path / "o" / "00.txt").read_bytes() == before
    r = runner.invoke(app, [*again, "--overwrite"])
    assert r.exit_code == 0 and (tmp_path / "o" / "00.txt").read_bytes() != before, r.output  # the guard changed it
    # a single run's options are refused, not ignored
    r = runner.invoke(app, [*again[:-2], "--start", "1", "--resume", "--viz", str(tmp_path / "v")])
    assert r.exit_code == 1 and "--start, --resume, --viz: for a single run; --sequences runs whole sequences" \
        in r.output, r.output


@pytest.mark.parametrize("extra, words", [(["--engine", "foo"], "--engine must be one of sequential, local, ray"),
                                          (["--workers", "0"], "--workers must be at least 1")])
def test_engine_and_workers_are_checked_before_the_progress_bar(tmp_path, extra, words):
    r = runner.invoke(app, ["run", "--kitti-root", str(tmp_path), "--sequences", "00", "--out-dir",
                            str(tmp_path / "o"), *extra])
    assert r.exit_code == 1 and words in r.output and "chunks" not in r.output, r.output


def test_many_sequences_warn_of_ground_truth_that_does_not_fit_and_score_the_rest(tmp_path):
    """As a single run: a poses/NN.txt of another length is a warning before the work and that
    sequence goes unscored; a sequence without one is named; the others are scored."""
    from conftest import ROOT

    tiny = ROOT / "tests" / "data" / "tiny_seq"
    root = tmp_path / "kitti"
    (root / "poses").mkdir(parents=True)
    for n in ("00", "01", "02"):
        shutil.copytree(tiny, root / "sequences" / n, ignore=shutil.ignore_patterns("poses.txt"))
    shutil.copy(tiny / "poses.txt", root / "poses" / "00.txt")
    (root / "poses" / "01.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
    r = runner.invoke(app, ["run", "--kitti-root", str(root), "--sequences", "00-02", "--out-dir", str(tmp_path / "o"),
                            "--engine", "sequential", "--backend", "onnxruntime"])
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())
    assert "01.txt: 2 poses for a sequence of 3 frames" in text and "sequence 01 runs without scoring" in text, r.output
    assert text.index("runs without scoring") < text.index("sequences in")  # before the work
    assert "not scored (ground truth that does not fit): 01" in text and "not scored (no ground truth): 02" in text
    assert "│ 00 │ 3 │" in text, r.output
