"""The no-learning direct tracker (the network's reference) recovers the renderer's motion."""

from __future__ import annotations

import numpy as np
from typer.testing import CliRunner

from cli.main import app
from d3lvo_deploy.direct import DirectOdometry, pyramid
from d3lvo_deploy.geometry import relatives, rotation_angle
from d3lvo_deploy.poses import read_poses
from d3lvo_deploy.sequence import KittiSequence


def test_pyramid_cells_sit_on_multiples_of_the_stride():
    """A ramp u + 10 v stays the same ramp at each level (cell (i, j) is pixel (s i, s j))."""
    v, u = np.mgrid[0:64, 0:96].astype(np.float32)
    lv = pyramid(u + 10 * v, (4,))[0]
    i, j = 5, 7
    assert abs(lv.grey[i, j] - (4 * j + 40 * i)) < 1e-3
    assert abs(lv.gx[i, j] - 4.0) < 1e-3 and abs(lv.gy[i, j] - 40.0) < 1e-3  # per cell


def test_direct_tracker_follows_the_rendered_motion(small_synth):
    seq = KittiSequence.open(small_synth)
    odo = DirectOdometry(seq.calib)
    est = np.stack([odo.step(seq.image(i), seq.scan(i)) for i in range(len(seq))])
    gt_rel = relatives(seq.ground_truth.poses)
    err = relatives(est)
    t_err = np.linalg.norm(err[:, :3, 3] - gt_rel[:, :3, 3], axis=1)
    r_err = np.degrees(rotation_angle(np.swapaxes(err[:, :3, :3], 1, 2) @ gt_rel[:, :3, :3]))
    no_motion_t = np.linalg.norm(gt_rel[:, :3, 3], axis=1)
    print("per-pair translation error (m)", t_err.round(4), "no motion", no_motion_t.round(3))
    print("per-pair rotation error (deg)", r_err.round(4))
    assert np.all(t_err < 0.1 * no_motion_t)  # within a tenth of the motion itself
    assert np.all(r_err < 0.1)


def test_cli_run_method_direct_scores(small_synth, tmp_path):
    r = CliRunner().invoke(app, ["run", "--seq-dir", str(small_synth), "--method", "direct", "--out", str(tmp_path / "d.txt")])
    assert r.exit_code == 0, r.output
    assert len(read_poses(tmp_path / "d.txt")) == 6 and "RPE" in r.output
    r = CliRunner().invoke(app, ["run", "--seq-dir", str(small_synth), "--method", "orb", "--out", str(tmp_path / "e.txt")])
    assert r.exit_code == 1 and "--method must be d3lvo or direct" in r.output
