"""The runtime package must import and work on a vehicle without torch."""

import subprocess
import sys
import textwrap

from conftest import ROOT


def test_every_runtime_module_imports_without_torch():
    script = textwrap.dedent(
        """
        import importlib, pkgutil, sys

        class BlockTorch:
            def find_spec(self, name, path=None, target=None):
                if name == "torch" or name.startswith("torch."):
                    raise ImportError("torch is blocked in this test")
                return None

        sys.meta_path.insert(0, BlockTorch())
        import d3lvo_deploy
        names = [m.name for m in pkgutil.walk_packages(d3lvo_deploy.__path__, "d3lvo_deploy.")]
        for n in names:
            importlib.import_module(n)
        assert "torch" not in sys.modules
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
