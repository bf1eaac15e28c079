"""Reading KITTI odometry folders, and one clear error for each kind of broken folder."""

import shutil

import numpy as np
import pytest
from conftest import shared_path

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.sequence import KittiSequence


def test_real_snippet_reads():
    seq = KittiSequence.open(shared_path("kitti_raw_snippet", "sequences", "r0926"))
    assert len(seq) == 20
    assert seq.image(0).shape == (375, 1242, 3)
    assert seq.scan(19).shape[1] == 4
    assert seq.ground_truth is None  # the README says: no GT for this drive


def test_kitti_root_layout_finds_poses(small_synth, tmp_path):
    root = tmp_path / "kitti"
    shutil.copytree(small_synth, root / "sequences" / "09")
    (root / "poses").mkdir()
    shutil.move(root / "sequences" / "09" / "poses.txt", root / "poses" / "09.txt")
    seq = KittiSequence.from_kitti_root(root, "09")
    assert seq.gt_path == root / "poses" / "09.txt"
    assert len(seq.ground_truth) == len(seq)


@pytest.fixture
def broken(small_synth, tmp_path):
    dst = tmp_path / "seq"
    shutil.copytree(small_synth, dst)
    return dst


def _fails(path, *words):
    with pytest.raises(D3LVOInputError) as e:
        KittiSequence.open(path)
    for w in words:
        assert w in str(e.value)


def test_missing_scan(broken):
    (broken / "velodyne" / "000003.bin").unlink()
    _fails(broken, "6 images but 5 scans", "000003")


def test_missing_frame_in_the_middle(broken):
    (broken / "velodyne" / "000003.bin").unlink()
    (broken / "image_2" / "000003.png").unlink()
    _fails(broken, "000002 to 000004")


def test_missing_calib(broken):
    (broken / "calib.txt").unlink()
    _fails(broken, "calib.txt", "not found")


def test_times_count(broken):
    (broken / "times.txt").write_text("0.0\n0.1\n")
    _fails(broken, "times.txt", "2 timestamps for 6 frames")


@pytest.mark.parametrize("text, words", [
    ("0.0\n0.1\nabc\n0.3\n0.4\n0.5\n", ["times.txt", "line 3", "'abc' is not a time in seconds"]),
    ("0.0\n0.1\n0.3\n0.2\n0.4\n0.5\n", ["times.txt", "line 4", "0.2 s does not come after 0.3 s"]),
])
def test_times_errors_name_the_line(broken, text, words):
    (broken / "times.txt").write_text(text)
    _fails(broken, *words)
    with pytest.raises(D3LVOInputError) as e:
        KittiSequence.open(broken)
    assert "numpy" not in str(e.value) and "loadtxt" not in str(e.value)


def test_times_in_another_unit_warn(broken):
    """Times in milliseconds (100 a frame at 10 Hz) are read, but said to be in the wrong unit:
    --realtime would wait 100 s a frame, and TUM poses would carry them; seconds say nothing."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        KittiSequence.open(broken)  # the fixture's 0.1 s steps
    (broken / "times.txt").write_text("".join(f"{100.0 * i}\n" for i in range(6)))
    with pytest.warns(UserWarning, match=r"times.txt: its frames are 100 apart \(median\): times are read as seconds"):
        seq = KittiSequence.open(broken)
    np.testing.assert_array_equal(seq.times, 100.0 * np.arange(6))


def test_greyscale_images_warn_once_and_read_as_rgb(broken):
    import warnings

    import cv2

    from d3lvo_deploy.sequence import GreyscaleWarning

    colour = KittiSequence.open(broken).image(1)
    for i in range(6):
        p = broken / "image_2" / f"{i:06d}.png"
        cv2.imwrite(str(p), cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2GRAY))
    seq = KittiSequence.open(broken)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        imgs = [seq.image(i) for i in range(3)]
    grey = [w for w in caught if issubclass(w.category, GreyscaleWarning)]
    assert len({str(w.message) for w in grey}) == 1 and "image_0" in str(grey[0].message)
    assert imgs[1].shape == colour.shape and np.array_equal(imgs[1][..., 0], imgs[1][..., 2])
    expect = cv2.cvtColor(cv2.cvtColor(colour, cv2.COLOR_RGB2BGR), cv2.COLOR_BGR2GRAY)
    assert np.array_equal(imgs[1][..., 0], expect)
    # a run reads the frames in several steps (the first frame's checks, the run): the warning once
    from typer.testing import CliRunner

    from cli.main import app

    r = CliRunner().invoke(app, ["run", str(broken), "--method", "direct", "--out", str(broken / "p.txt")])
    assert r.exit_code == 0 and r.output.count("greyscale images") == 1, r.output


def test_gt_count(broken):
    (broken / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    seq = KittiSequence.open(broken)
    with pytest.raises(D3LVOInputError, match="3 poses for a sequence of 6"):
        seq.ground_truth


def test_corrupt_png(broken):
    (broken / "image_2" / "000002.png").write_bytes(b"not a png at all")
    seq = KittiSequence.open(broken)
    with pytest.raises(D3LVOInputError, match="000002.png.*decoded"):
        seq.image(2)


def test_truncated_scan(broken):
    f = broken / "velodyne" / "000001.bin"
    f.write_bytes(f.read_bytes()[:-6])
    seq = KittiSequence.open(broken)
    with pytest.raises(D3LVOInputError, match="000001.bin"):
        seq.scan(1)
    assert np.isfinite(seq.scan(0)).all()
