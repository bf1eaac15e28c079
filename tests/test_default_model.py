"""The bundled default model: present, verified, equal to its shipped checkpoint, and the demo runs."""

from typer.testing import CliRunner

from cli.main import app
from d3lvo_deploy.bundled import BUNDLED, bundled_model_dir
from d3lvo_deploy.manifest import load_manifest

runner = CliRunner()


def test_bundled_model_is_shipped_and_verified():
    m = load_manifest(bundled_model_dir())
    assert m["precision"] == "fp32" and m["model_config"]["mode"] == "rgb_completion"
    assert (BUNDLED / "MODEL_CARD.md").is_file()
    size = sum((BUNDLED / s["file"]).stat().st_size for s in m["stages"].values())
    assert size < 20e6  # "a few MB"


def test_bundled_onnx_matches_its_checkpoint(small_synth):
    from export.parity import run_parity

    rep = run_parity(BUNDLED / "default.pt", BUNDLED, small_synth, frames=3)
    assert rep.passed, rep.to_dict()


def test_demo_runs_end_to_end(tmp_path):
    r = runner.invoke(app, ["demo", "--out", str(tmp_path / "demo"), "--frames", "12"])
    assert r.exit_code == 0, r.output
    assert "ATE m" in r.output and "latency" in r.output
    assert (tmp_path / "demo" / "synthetic_heldout.png").stat().st_size > 1000
    lines = (tmp_path / "demo" / "synthetic_heldout_poses.txt").read_text().splitlines()
    assert len(lines) == 12


def test_run_without_onnx_uses_the_bundled_model(small_synth, tmp_path):
    r = runner.invoke(app, ["run", "--seq-dir", str(small_synth), "--out", str(tmp_path / "p.txt")])
    assert r.exit_code == 0, r.output
    assert len((tmp_path / "p.txt").read_text().splitlines()) == 6
