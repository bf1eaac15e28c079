"""Every README block marked `<!-- runnable -->` runs as pasted: shell blocks in a fresh folder
(with the checkout's tests/data beside it, `d3lvo` from this install), Python blocks from the
checkout root."""

from __future__ import annotations

import contextlib
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT

BLOCK = re.compile(r"<!-- runnable -->\s*\n```(\w+)\n(.*?)```", re.S)


def runnable_blocks() -> list[tuple[str, str]]:
    return BLOCK.findall((ROOT / "README.md").read_text())


def test_the_readme_marks_blocks_to_run():
    kinds = [k for k, _ in runnable_blocks()]
    assert "bash" in kinds and "python" in kinds, kinds


@pytest.mark.parametrize("k", range(len(runnable_blocks())))
def test_readme_block_runs(k, tmp_path, monkeypatch):
    lang, code = runnable_blocks()[k]
    if lang == "python":
        monkeypatch.chdir(ROOT)
        with contextlib.redirect_stdout(io.StringIO()):
            exec(compile(code, f"README.md block {k}", "exec"), {})
        return
    assert lang == "bash", lang
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "data").symlink_to(ROOT / "tests" / "data")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    r = subprocess.run(["bash", "-euo", "pipefail", "-c", code], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
