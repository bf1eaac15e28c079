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


def make_checkpoint(path: Path, seed: int = 0, **cfg_kw) -> Path:
    """An untrained but deterministic small checkpoint (random BN statistics, so BN folding matters)."""
    import torch

    from models.checkpoint import save_checkpoint
    from models.config import D3LVOConfig
    from models.d3lvo import D3LVO

    torch.manual_seed(seed)
    cfg = D3LVOConfig.small(height=64, width=224, **cfg_kw)
    model = D3LVO(cfg).eval()
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
    save_checkpoint(path, model, cfg, step=7)
    return path


@pytest.fixture(scope="session")
def small_model(tmp_path_factory) -> tuple[Path, Path]:
    """(checkpoint, exported ONNX folder) of a small 224x64 model."""
    from export.onnx_export import ExportConfig, export_checkpoint

    d = tmp_path_factory.mktemp("model")
    ck = make_checkpoint(d / "ck.pt")
    export_checkpoint(ck, ExportConfig(out=d / "onnx"))
    return ck, d / "onnx"
