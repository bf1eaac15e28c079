"""The runtime package must import and work on a vehicle without torch."""

import subprocess
import sys
import textwrap

from conftest import ROOT


def test_every_runtime_module_imports_without_torch():
    script = textwrap.dedent(
        """
        import importlib, pkgutil, sys

        class Block:  # what a vehicle install lacks: the [train], [synth] and [plot] extras
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("torch", "onnx", "embreex", "matplotlib"):
                    raise ImportError(f"{name} is blocked in this test")
                return None

        sys.meta_path.insert(0, Block())
        import d3lvo_deploy
        names = [m.name for m in pkgutil.walk_packages(d3lvo_deploy.__path__, "d3lvo_deploy.")]
        for n in names:
            importlib.import_module(n)
        assert not {"torch", "onnx", "embreex", "matplotlib"} & set(sys.modules)
        # and it works: a projection and an evaluation run with torch unavailable
        import numpy as np
        from d3lvo_deploy.projection import sparse_depth
        from d3lvo_deploy.metrics import ate_rmse
        d = sparse_depth(np.array([[0.0, 0.0, 5.0]]), np.hstack([np.eye(3), np.zeros((3, 1))]), 4, 4)
        assert d[0, 0] == 5.0
        assert ate_rmse(np.tile(np.eye(4), (3, 1, 1)), np.tile(np.eye(4), (3, 1, 1))) == 0.0
        print(len(names))
        """
    )
    r = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.strip()) >= 10  # the walk really found the modules


def test_runtime_cli_runs_without_the_training_extras(small_synth, tmp_path):
    """A vehicle install (no [train], [synth], [plot], [openvino]): run (network and direct
    tracker), eval and bench work, on onnxruntime; commands that need an extra say which one in one
    line, exit 1, no traceback."""
    script = textwrap.dedent(
        """
        import sys
        BLOCKED = ("torch", "embreex", "matplotlib", "onnx", "openvino")

        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED:
                    raise ImportError(f"{name} is blocked in this test")
                return None

        sys.meta_path.insert(0, Block())
        from cli.main import main
        sys.argv = ["d3lvo"] + sys.argv[1:]
        main()
        """
    )

    def d3lvo(*args):
        return subprocess.run([sys.executable, "-c", script, *args], cwd=ROOT, capture_output=True, text=True)

    seq, est = str(small_synth), str(tmp_path / "p.txt")
    r = d3lvo("run", "--seq-dir", seq, "--out", est)
    assert r.returncode == 0, r.stderr
    assert len(open(est).read().splitlines()) == 6
    r = d3lvo("run", "--seq-dir", seq, "--method", "direct", "--out", str(tmp_path / "d.txt"))
    assert r.returncode == 0, r.stderr
    r = d3lvo("eval", "--gt", str(small_synth / "poses.txt"), "--est", est)
    assert r.returncode == 0 and "ATE" in r.stdout, r.stderr
    r = d3lvo("bench", "--no-torch", "--seq-dir", seq, "--runs", "2")
    assert r.returncode == 0 and "frames/s" in r.stdout and "openvino" not in r.stdout.lower(), r.stderr
    for args, extra in ((["train", "--data", seq, "--out", str(tmp_path / "c.pt")], "train"),
                        (["synth", "--out", str(tmp_path / "s"), "--frames", "2"], "synth"),
                        (["eval", "--gt", str(small_synth / "poses.txt"), "--est", est, "--plot", str(tmp_path / "x.png")], "plot"),
                        (["export", "--ckpt", "x.pt", "--out", str(tmp_path / "o")], "train")):
        r = d3lvo(*args)
        assert r.returncode == 1, (args, r.stderr)
        assert f"pip install 'd3lvo-deploy[{extra}]'" in r.stderr and "Traceback" not in r.stderr, r.stderr
