"""The `d3lvo` command: eval and synth end to end, JSON output, plots, and bad input without tracebacks."""

import json

import numpy as np
import pytest
from conftest import ROOT, shared_path
from typer.testing import CliRunner

from cli.main import app
from d3lvo_deploy.geometry import make_se3
from d3lvo_deploy.poses import read_poses, write_poses

runner = CliRunner()


def _straight(n, step):
    return np.stack([make_se3(np.eye(3), [0, 0, step * i]) for i in range(n)])


def test_eval_json_and_plot(tmp_path):
    gt, est = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_poses(gt, _straight(400, 1.0))
    write_poses(est, _straight(400, 1.01), fmt="tum")  # formats can differ
    plot = tmp_path / "traj.png"
    r = runner.invoke(app, ["eval", "--gt", str(gt), "--est", str(est), "--json", "--plot", str(plot)])
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    for key in ("t_rel", "r_rel", "ate", "rpe_t", "rpe_r", "segments"):
        assert key in data
    assert data["t_rel"] == pytest.approx(1.0, abs=0.02)
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # no suffix: a PNG named so, and said so; a suffix matplotlib does not write: refused before scoring
    r = runner.invoke(app, ["eval", "--gt", str(gt), "--est", str(est), "--plot", str(tmp_path / "cmp")])
    assert r.exit_code == 0 and f"plot written to {tmp_path / 'cmp.png'}" in r.output, r.output
    assert (tmp_path / "cmp.png").read_bytes()[:4] == b"\x89PNG"
    r = runner.invoke(app, ["eval", "--gt", str(gt), "--est", str(est), "--plot", str(tmp_path / "p.xyz")])
    assert r.exit_code == 1 and "--plot writes" in r.output and ".jpeg" in r.output and "not .xyz" in r.output, r.output
    r = runner.invoke(app, ["eval", "--gt", str(gt), "--est", str(est), "--plot", str(tmp_path / "p.jpeg")])
    assert r.exit_code == 0 and (tmp_path / "p.jpeg").read_bytes()[:2] == b"\xff\xd8", r.output  # a JPEG


def test_eval_folders(tmp_path):
    gt_dir = shared_path("kitti_gt_poses")
    r = runner.invoke(app, ["eval", "--gt", str(gt_dir), "--est", str(shared_path("kitti_results", "dfvo")), "--json"])
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert [s["name"] for s in data["sequences"]] == ["09", "10"]
    assert data["segments"] == sum(s["segments"] for s in data["sequences"])


def test_eval_folders_say_which_ground_truth_has_no_estimate(tmp_path):
    """Two methods compared on folders must be compared on the same sequences: a ground-truth file
    without an estimate of its name is named, not silently left out; --plot "" is one error."""
    gt_dir, est_dir = tmp_path / "gt", tmp_path / "est"
    gt_dir.mkdir(), est_dir.mkdir()
    for name in ("00.txt", "04.txt"):
        write_poses(gt_dir / name, _straight(50, 1.0))
    write_poses(est_dir / "00.txt", _straight(50, 1.1))
    r = runner.invoke(app, ["eval", "--gt", str(gt_dir), "--est", str(est_dir)])
    assert r.exit_code == 0 and "no estimate for 04.txt" in r.output and "not scored" in r.output, r.output
    # folders give the per-sequence JSON however many sequences pair up, one here
    r = runner.invoke(app, ["eval", "--gt", str(gt_dir), "--est", str(est_dir), "--json"])
    data = json.loads(r.stdout)
    assert [s["name"] for s in data["sequences"]] == ["00"], data
    assert data["ate"] == pytest.approx(data["sequences"][0]["ate"]), data
    write_poses(est_dir / "04.txt", _straight(50, 1.1))
    r = runner.invoke(app, ["eval", "--gt", str(gt_dir), "--est", str(est_dir)])
    assert r.exit_code == 0 and "no estimate" not in r.output, r.output
    pytest.importorskip("matplotlib")
    (est_dir / "04.txt").unlink()  # folders with one sequence in common: its plot is named by it too
    r = runner.invoke(app, ["eval", "--gt", str(gt_dir), "--est", str(est_dir), "--plot", str(tmp_path / "cmp.png")])
    assert r.exit_code == 0 and (tmp_path / "cmp_00.png").is_file() and not (tmp_path / "cmp.png").exists(), r.output
    r = runner.invoke(app, ["eval", "--gt", str(gt_dir / "00.txt"), "--est", str(est_dir / "00.txt"), "--plot", ""])
    assert r.exit_code == 1 and "--plot names no file" in r.output and "Traceback" not in r.output, r.output


def test_eval_table(tmp_path):
    gt, est = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_poses(gt, _straight(50, 1.0))
    write_poses(est, _straight(50, 1.1))
    r = runner.invoke(app, ["eval", "--gt", str(gt), "--est", str(est)])
    assert r.exit_code == 0
    assert "n/a" in r.output and "shorter than" in r.output  # 49 m path: no 100 m segment


@pytest.mark.parametrize(
    "setup, words",
    [
        (lambda d: (d / "gt.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5), ["est.txt", "not found"]),
        (lambda d: [(d / "gt.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5),
                    (d / "est.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 nan\n" * 5)], ["est.txt", "NaN"]),
        (lambda d: [(d / "gt.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5),
                    (d / "est.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 9)], ["est.txt", "only 5"]),
        # a folder of ground truth beside one estimate file
        (lambda d: [(d / "gt.txt").mkdir(), (d / "est.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5)],
         ["est.txt: is a file but --gt", "gt.txt is a folder"]),
    ],
)
def test_eval_bad_input_is_one_clear_line(tmp_path, setup, words):
    setup(tmp_path)
    r = runner.invoke(app, ["eval", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt")])
    assert r.exit_code == 1
    assert "Traceback" not in r.output
    for w in words:
        assert w in r.output


def test_eval_bad_align(tmp_path):
    r = runner.invoke(app, ["eval", "--gt", "a", "--est", "b", "--align", "9dof"])
    assert r.exit_code == 1 and "--align" in r.output


def test_synth_then_eval(tmp_path):
    out = tmp_path / "seq"
    r = runner.invoke(app, ["synth", "--out", str(out), "--frames", "3", "--size", "320x96", "--seed", "4"])
    assert r.exit_code == 0, r.output
    assert len(list((out / "image_2").glob("*.png"))) == 3 and f"wrote 3 frames to {out}" in r.output
    # run again, it says what it rendered: nothing, then the one frame taken away
    args = ["synth", "--out", str(out), "--frames", "3", "--size", "320x96", "--seed", "4"]
    r = runner.invoke(app, args)
    assert r.exit_code == 0 and "holds all 3 frames of these settings already: nothing rendered" in r.output, r.output
    (out / "image_2" / "000001.png").unlink()
    r = runner.invoke(app, args)
    assert r.exit_code == 0 and "wrote 1 frame to" in r.output and "the other 2 were there" in r.output, r.output
    # an estimate twice as long as the GT: ATE = RMS of the GT's distances from the start
    gt = read_poses(out / "poses.txt").poses
    est = gt.copy()
    est[:, :3, 3] *= 2.0
    write_poses(tmp_path / "est.txt", est)
    r = runner.invoke(app, ["eval", "--gt", str(out / "poses.txt"), "--est", str(tmp_path / "est.txt"), "--json"])
    assert r.exit_code == 0
    assert json.loads(r.stdout)["ate"] == pytest.approx(np.sqrt((gt[:, :3, 3] ** 2).sum(1).mean()), rel=1e-6)


def test_synth_bad_size_and_unwritable(tmp_path):
    r = runner.invoke(app, ["synth", "--out", str(tmp_path / "x"), "--size", "big"])
    assert r.exit_code == 1 and "--size" in r.output
    # settings the renderer refuses: one line, before any progress bar, nothing written
    for args, words in ((["--frames", "1"], "--frames must be at least 2"), (["--size", "40x20"], "too small"),
                        (["--traffic", "-1"], "--traffic must be 0 or more")):
        for command in (["synth", "--out", str(tmp_path / "y")], ["demo", "--out", str(tmp_path / "y")]):
            if command[0] == "demo" and args[0] != "--frames":
                continue  # the demo's drives have their own size and traffic
            r = runner.invoke(app, [*command, *args])
            assert r.exit_code == 1 and r.output.startswith("error: "), r.output
            assert words in r.output and len(r.output.strip().splitlines()) == 1, r.output
    assert not (tmp_path / "y").exists()
    blocker = tmp_path / "file"
    blocker.write_text("")
    r = runner.invoke(app, ["synth", "--out", str(blocker / "seq"), "--frames", "2", "--size", "320x96"])
    assert r.exit_code == 1 and "cannot create" in r.output and "Traceback" not in r.output
    r = runner.invoke(app, ["synth", "--out", str(blocker), "--frames", "2", "--size", "320x96"])  # before the bar
    assert r.exit_code == 1 and r.output.strip() == f"error: {blocker}: is a file: --out names the folder to render " \
                                                     "the sequence into", r.output
    r = runner.invoke(app, ["demo", "--out", str(blocker)])  # before any rendering
    assert r.exit_code == 1 and r.output.strip() == f"error: {blocker}: is a file; --out names the folder for the " \
                                                     "demo's drives, poses and plots", r.output


def test_eval_several_estimates_one_table_and_a_scale_hint(tmp_path):
    """Two --est give one table with a row each; a result up to scale (the monocular example,
    about 1/40 of GT's path) gets a hint to align, and scores the published 2.88 % with --align 7dof."""
    gt = shared_path("kitti_gt_poses", "09.txt")
    dfvo, mono = shared_path("kitti_results", "dfvo", "09.txt"), shared_path("kitti_results", "mono_example", "09.txt")
    r = runner.invoke(app, ["eval", "--gt", str(gt), "--est", str(dfvo), "--est", str(mono), "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)["estimates"]
    assert set(d) == {"dfvo/09", "mono_example/09"}
    assert abs(d["dfvo/09"]["t_rel"] - 2.61) < 0.01
    assert any("--align 7dof" in n for n in d["mono_example/09"]["notes"])
    assert not any("--align" in n for n in d["dfvo/09"]["notes"])
    r = runner.invoke(app, ["eval", "--gt", str(gt), "--est", str(dfvo), "--est", str(mono)])
    assert r.exit_code == 0 and "dfvo/09" in r.output and "mono_example/09" in r.output
    r = runner.invoke(app, ["eval", "--gt", str(gt), "--est", str(mono), "--align", "7dof", "--json"])
    res = json.loads(r.stdout)
    assert abs(res["t_rel"] - 2.88) < 0.01 and not any("--align" in n for n in res["notes"])


@pytest.mark.parametrize("command", ["demo", "synth", "train", "export", "parity", "run", "eval", "bench"])
def test_every_help_has_an_example_and_keeps_bracketed_words(command):
    r = runner.invoke(app, [command, "--help"], terminal_width=200)
    assert r.exit_code == 0
    assert f"Example: d3lvo {command}" in r.output, r.output
    if command == "run":  # rich markup would swallow "[rerun]" and "[openvino]"
        assert "[rerun]" in r.output and "[openvino]" in r.output


def test_top_level_help_lists_the_commands_in_workflow_order():
    r = runner.invoke(app, ["--help"], terminal_width=200)
    order = ["demo", "synth", "train", "export", "parity", "run", "eval", "bench"]
    listed = [line.split()[1] for line in r.output.splitlines() if line.startswith("│ ") and len(line.split()) > 1
              and line.split()[1] in order]
    assert listed == order, r.output


def test_help_paragraphs_wrap_at_the_terminal_width():
    from cli.main import one_line_paragraphs

    assert one_line_paragraphs("First\n    line.\n\n    More\n    text.\n    Example: d3lvo x\n") == \
        "First line.\n\nMore text.\nExample: d3lvo x"
    r = runner.invoke(app, ["--help"], terminal_width=80)
    # the docstring breaks "synth" and "(KITTI-format" apart; rich, wrapping the paragraph, does not
    assert "synth (KITTI-format synthetic drives)" in r.output, r.output


def test_parity_needs_a_pair_and_train_a_known_balance_start(tmp_path):
    r = runner.invoke(app, ["parity", "--ckpt", str(tmp_path / "a.pt"), "--onnx", str(tmp_path), "--frames", "1"])
    assert r.exit_code == 1 and "--frames must be at least 2 (one pair), not 1" in r.output, r.output
    cfg = tmp_path / "t.toml"
    cfg.write_text('[loss]\nbalance_init = "foo"\n')
    data = ROOT / "tests" / "data" / "tiny_seq"
    r = runner.invoke(app, ["train", "--config", str(cfg), "--data", str(data), "--out", str(tmp_path / "t.pt")])
    assert r.exit_code == 1 and "[loss] balance_init must be data or config, not 'foo'" in r.output, r.output
    assert not (tmp_path / "t.pt").exists()
