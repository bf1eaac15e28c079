"""Shared fixtures: the real KITTI files in ../shared/data (skipped when absent) and a tiny synthetic sequence."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"


def shared_path(*parts: str) -> Path:
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real KITTI data not available at {p} (../shared/data is absent)")
    return p


@pytest.fixture(scope="session")
def small_synth(tmp_path_factory) -> Path:
    """A 6-frame, 620x188 synthetic sequence, LiDAR without range noise so geometry checks are exact."""
    from d3lvo_deploy.synth.generator import SynthConfig, generate
    from d3lvo_deploy.synth.sensors import LidarConfig

    out = tmp_path_factory.mktemp("synth") / "seq"
    generate(out, SynthConfig(frames=6, seed=7, width=620, height=188, lidar=LidarConfig(noise_m=0.0, dropout=0.0)))
    return out
