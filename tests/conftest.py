"""Shared fixtures: the real KITTI files in ../shared/data (skipped when absent) and a tiny synthetic sequence."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"

# Under pytest-xdist the workers share the cores: torch's, onnxruntime's and OpenVINO's own thread
# per core in every worker would make threads fight over each core (on 2 cores with 2 workers that
# cost a third of the suite's CPU time). Each worker gets its share of the cores, unless
# OMP_NUM_THREADS is set already: torch reads it when first imported, the engines when `--threads`
# is 0 (SessionConfig.engine_threads). Set before any test module imports torch; a thread count a
# test asks for still applies.
_workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _workers > 1:
    _cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, _cores // _workers)))


def shared_path(*parts: str) -> Path:
    """A file of ../shared/data; the test skips where it is absent, and fails instead where
    D3LVO_REQUIRE_SHARED=1 (CI, which has the folder: a skip there would hide a broken path)."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        msg = f"real KITTI data not available at {p} (../shared/data is absent)"
        if os.environ.get("D3LVO_REQUIRE_SHARED") == "1":
            pytest.fail(msg + " but D3LVO_REQUIRE_SHARED=1")
        pytest.skip(msg)
    return p


@pytest.fixture(scope="session", autouse=True)
def _own_graph_cache(tmp_path_factory):
    """Each test process keeps its compiled and optimised graphs in its own folder: never the
    user's cache, never a file another pytest-xdist worker is writing."""
    os.environ["D3LVO_CACHE"] = str(tmp_path_factory.mktemp("d3lvo-cache"))


def built_once(tmp_path_factory, name: str, build: Callable[[Path], object]) -> Path:
    """A folder that `build` fills once per test run. Under pytest-xdist the first worker to ask
    builds it while the others wait, instead of each rendering or exporting the same thing again
    (pytest-xdist's documented recipe for session fixtures, with filelock). Tests only read it."""
    from filelock import FileLock

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, above every worker's own
    folder, done = root / "built-once" / name, root / "built-once" / f"{name}.done"
    folder.parent.mkdir(exist_ok=True)
    with FileLock(f"{done}.lock"):
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            done.touch()
    return folder


# What each pytest-xdist worker builds before its first test (gw0's ~30-40 s, gw1's ~22-28 s on
# an AMD EPYC): left to the tests, both workers asked for the point-solver exports at once and
# one waited ~25 s for the other. Each worker's first export traces before onnxruntime is loaded
# (no test module imports it at import time; the export's own checks load it), and a loaded
# onnxruntime slows each trace (docs/export-and-parity.md).
PREBUILT = {"gw0": ("points_model", "scan_judge_model"),
            "gw1": ("small_model", "small_synth", "traffic_clip", "turning_drives")}


@pytest.fixture(scope="session", autouse=True)
def _prebuilt(request, _own_graph_cache):
    """This worker's share of the shared fixtures that the collected tests use (none for a run
    without workers, or of tests that use none of them). A build that skips (an optional extra
    missing) or fails is left to the tests that use it: pytest keeps the outcome and gives it to
    them, not to every test of this worker."""
    used = {name for item in request.session.items for name in getattr(item, "fixturenames", ())}
    for name in PREBUILT.get(os.environ.get("PYTEST_XDIST_WORKER", ""), ()):
        if name in used:
            try:
                request.getfixturevalue(name)
            except (Exception, pytest.skip.Exception, pytest.fail.Exception):
                pass


@pytest.fixture(autouse=True)
def _seeded():
    """Every test starts from the same torch seed, so that a model a test builds does not depend
    on which tests ran before it."""
    import torch

    torch.manual_seed(0)


@pytest.fixture(scope="session")
def small_synth(tmp_path_factory) -> Path:
    """A 6-frame, 620x188 synthetic sequence, LiDAR without range noise so geometry checks are exact."""
    from d3lvo_deploy.synth.generator import SynthConfig, generate
    from d3lvo_deploy.synth.sensors import LidarConfig

    cfg = SynthConfig(frames=6, seed=7, width=620, height=188, lidar=LidarConfig(noise_m=0.0, dropout=0.0))
    return built_once(tmp_path_factory, "synth", lambda d: generate(d / "seq", cfg)) / "seq"


def render_turning_drive(out: Path, frames: int, phase: float, seed: int) -> Path:
    """A synthetic sequence whose camera turns left and right (yaw +-2 deg per frame) at a varying
    speed (0.5-1.1 m per frame): motion that differs between pairs, so no constant predicts it."""
    import numpy as np

    from d3lvo_deploy.geometry import accumulate, axis_angle_to_rot, make_se3
    from d3lvo_deploy.poses import write_poses
    from d3lvo_deploy.synth.generator import SynthConfig, generate

    k = np.arange(frames - 1)
    yaw = np.radians(2.0 * np.sin(0.7 * k + phase))
    forward = 0.8 + 0.3 * np.cos(0.5 * k + phase)
    rel = np.array([make_se3(axis_angle_to_rot([0.0, y, 0.0]), [0.0, 0.0, f]) for y, f in zip(yaw, forward)])
    gt = out.parent / f"{out.name}_motion.txt"
    write_poses(gt, accumulate(rel))
    return generate(out, SynthConfig(frames=frames, seed=seed, width=620, height=188, motion_from=str(gt)))


@pytest.fixture(scope="session")
def turning_drives(tmp_path_factory) -> tuple[Path, Path]:
    """(training, held-out) turning drives: other phases of the motion, other worlds."""
    d = built_once(tmp_path_factory, "turning", lambda d: (render_turning_drive(d / "train", 12, 0.0, 31),
                                                           render_turning_drive(d / "heldout", 7, 1.3, 32)))
    return d / "train", d / "heldout"


def make_checkpoint(path: Path, seed: int = 0, **cfg_kw) -> Path:
    """An untrained but deterministic small checkpoint (random BN statistics, so BN folding matters).
    Two Gauss-Newton steps per level unless a test asks otherwise: the second still starts from the
    first's pose, and the unrolled graph exports in half the time of the default four."""
    import torch

    from models.checkpoint import save_checkpoint
    from models.config import D3LVOConfig
    from models.d3lvo import D3LVO

    torch.manual_seed(seed)
    cfg = D3LVOConfig.small(height=64, width=224, **{"gn_iters": 2, **cfg_kw})
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

    d = built_once(tmp_path_factory, "model",
                   lambda d: export_checkpoint(make_checkpoint(d / "ck.pt"), ExportConfig(out=d / "onnx")))
    return d / "ck.pt", d / "onnx"


@pytest.fixture(scope="session")
def points_model(tmp_path_factory):
    """(checkpoint, ONNX folder) of an untrained 224x64 point-solver model, 6 Gauss-Newton steps per
    level instead of 15 (two blocks of 3, so the graph holds the solver's Loops): 6 steps from the
    constant-velocity start still converge on the test drive's small motions. With the finest
    level's restart from the start and its check against frame t's scan, as the bundled model, so
    that its graphs are tested too (ratio 1: the restart is kept wherever it fits the scan better).
    Exported with a dynamic batch: the runtime feeds it batches of one, the batched test two
    pairs, from the one export."""
    from export.onnx_export import ExportConfig, export_checkpoint

    d = built_once(tmp_path_factory, "points_model", lambda d: export_checkpoint(
        make_checkpoint(d / "ck.pt", pose_head="points", pt_iters=(6, 6, 6), pt_fine_restart=0.001,
                        pt_restart_depth=1.0),
        ExportConfig(out=d / "onnx", dynamic_batch=True)))
    return d / "ck.pt", d / "onnx"


@pytest.fixture(scope="session")
def scan_judge_model(points_model, tmp_path_factory):
    """(checkpoint, ONNX folder): `points_model` with `pt_select_scan_pass` 1 and pt_select 0.999
    (the photometric test never passes), without the restart, so that frame t's scan is read for
    the choice between the weighted and the classical pose alone; its last confidence layer
    redrawn at std 3, as in the rotation gate's test: an untrained confidence is the same on every
    point, and the two solves then agree. Its classical solve is a stage of its own, as the bundled
    model's, and starts from the previous classical pose (`pt_classical_chain`, which the bundled
    model leaves off); it holds the weighted pose one pair after each it keeps (`pt_select_hold`),
    so that its graph says which pose it kept."""
    from export.onnx_export import ExportConfig, export_checkpoint
    from models.checkpoint import build_model, load_checkpoint, save_checkpoint
    from models.d3lvo import D3LVO

    def build(d):
        from dataclasses import replace

        import torch

        # two pyramid levels: the choice between the poses is what is tested; each level is graph to export
        solver = dict(pt_fine_restart=0.0, pt_restart_depth=0.0, pt_select=0.999, pt_select_scan_pass=1.0,
                      pt_iters=(6, 6), pt_classical_chain=True, pt_select_hold=1)
        fixture = build_model(load_checkpoint(points_model[0]))
        model = D3LVO(replace(fixture.cfg, **solver)).eval()
        model.load_state_dict(fixture.state_dict())
        torch.manual_seed(1)
        with torch.no_grad():
            model.point_pose.moving.net[-1].weight.normal_(std=3.0)
            model.point_pose.moving.net[-1].bias.zero_()
        save_checkpoint(d / "ck.pt", model, model.cfg, step=0)
        export_checkpoint(d / "ck.pt", ExportConfig(out=d / "o"))

    d = built_once(tmp_path_factory, "scan_judge_model", build)
    return d / "ck.pt", d / "o"


@pytest.fixture(scope="session")
def traffic_clip(tmp_path_factory) -> Path:
    """8 frames at 416x128 with 6 vehicles per 100 m, LiDAR without range noise or dropout (the
    geometry checks are exact)."""
    pytest.importorskip("embreex")
    from d3lvo_deploy.synth.generator import SynthConfig, generate
    from d3lvo_deploy.synth.sensors import LidarConfig

    cfg = SynthConfig(frames=8, seed=21, width=416, height=128, traffic=6.0, lidar=LidarConfig(noise_m=0.0, dropout=0.0))
    return built_once(tmp_path_factory, "traffic", lambda d: generate(d / "seq", cfg)) / "seq"
