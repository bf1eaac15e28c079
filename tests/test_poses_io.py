"""Trajectory files: KITTI, indexed KITTI (kitti-odom-eval) and TUM, and their errors."""

import numpy as np
import pytest
from conftest import shared_path

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.geometry import axis_angle_to_rot, make_se3
from d3lvo_deploy.poses import read_poses, write_poses


def _traj(n=5):
    return np.stack([make_se3(axis_angle_to_rot([0.1 * i, -0.05 * i, 0.02]), [i, 0.5 * i, -i]) for i in range(n)])


@pytest.mark.parametrize("fmt", ["kitti", "tum"])
def test_round_trip(tmp_path, fmt):
    poses = _traj()
    f = tmp_path / f"t.{fmt}"
    write_poses(f, poses, fmt)
    back = read_poses(f)
    np.testing.assert_allclose(back.poses, poses, atol=1e-8)
    if fmt == "tum":
        np.testing.assert_allclose(back.timestamps, np.arange(5) * 0.1)


def test_kitti_line_layout_is_row_major(tmp_path):
    f = tmp_path / "one.txt"
    f.write_text("0 -1 0 4 1 0 0 8 0 0 1 12\n")  # 90 deg about z, t = (4, 8, 12)
    T = read_poses(f).poses[0]
    np.testing.assert_array_equal(T[:3], [[0, -1, 0, 4], [1, 0, 0, 8], [0, 0, 1, 12]])
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def test_tum_quaternion_order(tmp_path):
    f = tmp_path / "tum.txt"
    s = np.sqrt(0.5)
    f.write_text(f"0.5 1 2 3 0 0 {s} {s}\n")  # qx qy qz qw: 90 deg about z
    t = read_poses(f)
    np.testing.assert_allclose(t.poses[0][:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(t.poses[0][:3, 3], [1, 2, 3])
    assert t.timestamps[0] == 0.5


def test_indexed_rows_with_skipped_frames():
    t = read_poses(shared_path("kitti_results", "mono_example", "09.txt"))
    gt = read_poses(shared_path("kitti_gt_poses", "09.txt"))
    assert len(t) == 1589 and len(gt) == 1591
    assert t.frame_ids[0] > 0 and np.all(np.diff(t.frame_ids) >= 1)
    assert t.frame_ids[-1] <= 1590


@pytest.mark.parametrize(
    "text, words",
    [
        ("", "empty"),
        ("1 2 3\n", "3 columns"),
        ("1 2 3 4 5 6 7 8 9 10 11 12\n1 2 3\n", "line 2 has 3 numbers where the others have 12 (column counts [3, 12])"),
        ("# c\n1 0 0 0 0 1 0 0 0 0 1 0\n\n1 0 0 0 0 1 0 0 0 0 1\n1 0 0 0 0 1 0 0 0 0 1 0\n",
         "line 4 has 11 numbers where the others have 12"),
        ("1 2 3 4 5 6 7 8 9 10 11 nan\n", "NaN"),
        ("1 2 3 4 5 6 7 8 9 10 11 x\n", "line 1"),
        ("3 1 0 0 0 0 1 0 0 0 0 1 0\n2 1 0 0 0 0 1 0 0 0 0 1 0\n", "increasing"),
        # lines that are no pose: not a rotation (a reflection or zeros neither), a zero quaternion, time
        # going back; a rotation written with two decimals is one
        ("1 2 3 4 5 6 7 8 9 10 11 12\n", "pose 0: its 3x3 block is not a rotation"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n5 5 5 5 5 5 5 5 5 5 5 5\n", "pose 1: its 3x3 block is not a rotation"),
        ("-1 0 0 0 0 1 0 0 0 0 1 0\n", "pose 0: its 3x3 block is not a rotation (its determinant is -1)"),
        ("0 0 0 1 0 0 0 2 0 0 0 3\n", "pose 0: its 3x3 block is not a rotation (its determinant is 0)"),
        ("0.1 0 0 0 0 0 0 1\n0.2 0 0 0 0 0 0 0\n", "pose 1: its quaternion qx qy qz qw is all zero"),
        ("0.2 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n", "pose 1: its time does not come after"),
    ],
)
def test_bad_files_name_the_file(tmp_path, text, words):
    f = tmp_path / "bad.txt"
    f.write_text(text)
    with pytest.raises(D3LVOInputError) as e:
        read_poses(f)
    assert "bad.txt" in str(e.value) and words in str(e.value)


@pytest.mark.parametrize("encoding", ["utf-8-sig", "utf-16"])
def test_files_saved_with_a_byte_order_mark_read_as_plain_ones(tmp_path, encoding):
    """Notepad's UTF-8 with a BOM and PowerShell's UTF-16 give the same poses as plain text."""
    text = "1 0 0 0.5 0 1 0 0 0 0 1 2\r\n1 0 0 1.5 0 1 0 0 0 0 1 3\r\n"
    (tmp_path / "plain.txt").write_text(text, encoding="utf-8")
    (tmp_path / "bom.txt").write_text(text, encoding=encoding)
    np.testing.assert_array_equal(read_poses(tmp_path / "bom.txt").poses, read_poses(tmp_path / "plain.txt").poses)
    assert read_poses(tmp_path / "bom.txt").poses[1, 0, 3] == 1.5


def test_a_rotation_written_with_two_decimals_is_read(tmp_path):
    """Published trajectories are sometimes rounded: 37 degrees about y to two decimals puts R R^T
    about 0.01 from I, a rotation all the same."""
    a = np.radians(37.0)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    f = tmp_path / "rounded.txt"
    f.write_text(" ".join(f"{v:.2f}" for v in np.hstack([R, [[1.0], [2.0], [3.0]]]).reshape(-1)) + "\n")
    np.testing.assert_allclose(read_poses(f).poses[0][:3, :3], np.round(R, 2))
