"""ONNX export: standard ops only, checker, manifest, parity with torch, and clear errors."""

import json
import re
import shutil

import numpy as np
import onnx
import pytest
import torch
from conftest import make_checkpoint
from typer.testing import CliRunner

from cli.main import app
from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.manifest import graph_files, load_manifest
from d3lvo_deploy.onnx_model import StageModel
from export.onnx_export import ExportConfig, export_checkpoint, non_standard_nodes
from export.parity import run_parity
from models.checkpoint import save_checkpoint
from models.config import D3LVOConfig
from models.d3lvo import D3LVO

runner = CliRunner()


def _ckpt(tmp_path, name="ck.pt", **kw):
    p = make_checkpoint(tmp_path / name, **kw)
    return p, None


@pytest.fixture(scope="module")
def exported(small_model):
    ck, out = small_model
    return ck, out, json.loads((out / "manifest.json").read_text())


def test_three_standard_graphs_with_manifest(exported):
    ck, out, m = exported
    assert set(m["stages"]) == {"completion", "encoder", "flowpose"}
    for st in m["stages"].values():
        model = onnx.load(str(out / st["file"]))
        onnx.checker.check_model(model, full_check=True)
        assert non_standard_nodes(model) == []
        assert all(n.domain in ("", "ai.onnx") for n in model.graph.node)
        assert {o.domain for o in model.opset_import} <= {"", "ai.onnx"}
        meta = {p.key: p.value for p in model.metadata_props}
        assert json.loads(meta["d3lvo_config"])["width"] == 224
    assert m["checkpoint"]["step"] == 7 and m["depth_input"] == "sparse"
    assert m["stages"]["flowpose"]["outputs"][-1]["name"] == "matrix"
    assert m["stages"]["flowpose"]["outputs"][-1]["shape"] == [1, 4, 4]
    load_manifest(out)  # verifies hashes


def test_walker_catches_custom_domains():
    node = onnx.helper.make_node("Correlation", ["a"], ["b"], domain="com.example")
    g = onnx.helper.make_graph([node], "g", [onnx.helper.make_tensor_value_info("a", onnx.TensorProto.FLOAT, [1])],
                               [onnx.helper.make_tensor_value_info("b", onnx.TensorProto.FLOAT, [1])])
    assert non_standard_nodes(onnx.helper.make_model(g)) == ["Correlation (domain 'com.example')"]


def test_parity_reduced_size(exported, small_synth):
    """ONNX against D3LVO.forward (no export wrapper on the reference side) on pairs whose motion
    is far above the tolerance: the Gauss-Newton head responds to its input even untrained, and
    flows and confidences are compared as well (an untrained pose barely depends on the features)."""
    from export.parity import POSE_R_TOL, POSE_T_TOL

    ck, out, _ = exported
    rep = run_parity(ck, out, small_synth, frames=3)
    assert rep.passed, rep.to_dict()
    assert rep.stages["flowpose"]["matrix"].max_abs < 1e-4
    assert rep.chained_t_m <= POSE_T_TOL and rep.chained_r_deg <= POSE_R_TOL
    assert rep.reference_t_m <= POSE_T_TOL and rep.reference_r_deg <= POSE_R_TOL
    assert rep.motion_t_m > 1000 * POSE_T_TOL, rep.to_dict()
    # flows and confidences of the ONNX chain are compared with forward's too, output by output
    assert {"flow_l1", "confidence_l1"} <= set(rep.stages["vs_forward"])


# The other modes' own tests on two flow levels and one Gauss-Newton step per level (the fixture
# tests the whole pyramid): what they change is the graph's inputs and the encoder's, and this
# graph exports in half the time (rgb_sparse alone on an Intel Xeon: 7.1 against 15.4 s).
LEAN = dict(flow_levels=(3, 2), gn_iters=1)


@pytest.mark.parametrize("kw", [dict(mode="rgb"), dict(mode="rgb_sparse"), dict(completion="ipbasic"),
                                dict(pose_head="mlp")])
def test_parity_other_modes(tmp_path, small_synth, kw):
    ck, cfg = _ckpt(tmp_path, **LEAN, **kw)
    m = export_checkpoint(ck, ExportConfig(out=tmp_path / "onnx"))
    assert ("completion" in m["stages"]) == (kw == dict(pose_head="mlp"))
    inputs = [i["name"] for i in m["stages"]["flowpose"]["inputs"]]
    assert ("init_pose" in inputs) == (kw.get("mode") != "rgb" and kw.get("pose_head") != "mlp")
    rep = run_parity(ck, tmp_path / "onnx", small_synth, frames=2)
    assert rep.passed, rep.to_dict()


def test_export_converts_only_an_fp32_folder_as_exported(small_model, tmp_path):
    """`d3lvo export --onnx DIR --precision P`: a reduced-precision copy of an fp32 export, no
    checkpoint needed; anything that would need a new export, or would overwrite or re-convert
    the folder, is one line naming what is wrong."""
    ck, fp32_dir = small_model
    fp16 = tmp_path / "fp16"
    r = runner.invoke(app, ["export", "--onnx", str(fp32_dir), "--out", str(fp16), "--precision", "fp16"])
    assert r.exit_code == 0, r.output
    assert load_manifest(fp16)["precision"] == "fp16"
    cases = [(["--onnx", str(fp32_dir), "--out", str(tmp_path / "a")], "needs --precision fp16 or int8"),
             (["--onnx", str(fp16), "--out", str(tmp_path / "b"), "--precision", "int8"], "holds an fp16 model"),
             (["--onnx", str(fp32_dir), "--out", str(tmp_path / "c"), "--precision", "fp16", "--width", "256"],
              "--width needs --ckpt"),
             (["--onnx", str(fp32_dir), "--out", str(tmp_path / "c"), "--precision", "fp16", "--opset", "17"],
              "--opset needs --ckpt"),
             (["--onnx", str(fp32_dir), "--out", str(fp32_dir), "--precision", "fp16"], "the --onnx folder itself"),
             (["--onnx", str(tmp_path / "none"), "--out", str(tmp_path / "d"), "--precision", "fp16"],
              "model folder not found"),
             (["--onnx", str(tmp_path), "--out", str(tmp_path / "d"), "--precision", "fp16"], "no manifest.json"),
             (["--out", str(tmp_path / "e"), "--precision", "fp16"], "either --ckpt"),
             (["--ckpt", str(ck), "--onnx", str(fp32_dir), "--out", str(tmp_path / "f")], "either --ckpt")]
    before = {f.name: f.read_bytes() for f in fp32_dir.iterdir() if f.is_file()}
    for args, message in cases:
        r = runner.invoke(app, ["export", *args])
        assert r.exit_code == 1 and message in r.output and isinstance(r.exception, SystemExit), (args, r.output)
    # nothing written on a refusal, the --onnx folder left as it was
    assert not any((tmp_path / x).exists() for x in "abcdef")
    assert {f.name: f.read_bytes() for f in fp32_dir.iterdir() if f.is_file()} == before


def test_export_replaces_an_earlier_export_only_when_asked_and_only_once_complete(small_model, tmp_path,
                                                                                    monkeypatch):
    """An export into a folder that holds one needs --overwrite, into a folder of other files is
    refused, and one that stops half way (here the conversion, after writing its first file)
    leaves the earlier export whole and no partial folder behind; a complete one replaces it."""
    _, fp32_dir = small_model
    out = tmp_path / "m"
    convert = ["export", "--onnx", str(fp32_dir), "--precision", "fp16", "--out", str(out)]
    assert runner.invoke(app, convert).exit_code == 0
    before = {f.name: f.read_bytes() for f in out.iterdir()}
    r = runner.invoke(app, convert)
    assert r.exit_code == 1 and "already holds an export; --overwrite replaces it" in r.output, r.output
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    r = runner.invoke(app, [*convert[:-1], str(tmp_path / "mine"), "--overwrite"])
    assert r.exit_code == 1 and "holds files but no manifest.json" in r.output, r.output
    assert (tmp_path / "mine" / "notes.txt").read_text() == "mine"

    import export.quantize

    real = export.quantize.quantize_folder

    def stopped(src, dst, *a, **k):
        dst.mkdir(parents=True, exist_ok=True)
        (dst / "completion.onnx").write_bytes(b"half")
        raise KeyboardInterrupt

    monkeypatch.setattr(export.quantize, "quantize_folder", stopped)
    r = runner.invoke(app, [*convert, "--overwrite"])
    assert r.exit_code == 130, r.output
    assert {f.name: f.read_bytes() for f in out.iterdir()} == before  # no staging folder left either
    load_manifest(out)  # every hash still holds
    assert sorted(x.name for x in tmp_path.iterdir()) == ["m", "mine"]
    monkeypatch.setattr(export.quantize, "quantize_folder", real)
    # a complete export replaces the earlier one's graphs, drops a graph only the earlier one had,
    # and keeps what is not the export's (as the bundled folder's model card and checkpoint)
    (out / "MODEL_CARD.md").write_text("kept")
    (out / "encoder.onnx").write_bytes(b"earlier")
    (out / "extra.onnx").write_bytes(b"earlier")
    m = json.loads(before["manifest.json"])
    m["stages"]["extra"] = {"file": "extra.onnx"}
    (out / "manifest.json").write_text(json.dumps(m))
    r = runner.invoke(app, [*convert, "--overwrite"])
    assert r.exit_code == 0, r.output
    assert (out / "encoder.onnx").read_bytes() == before["encoder.onnx"] and not (out / "extra.onnx").exists()
    assert (out / "MODEL_CARD.md").read_text() == "kept"
    load_manifest(out)
    assert sorted(x.name for x in out.iterdir()) == sorted([*before, "MODEL_CARD.md"])  # no staging folder
    assert sorted(x.name for x in tmp_path.iterdir()) == ["m", "mine"]


def test_export_refuses_what_it_cannot_export(tmp_path):
    """A checkpoint with NaN weights, an opset past the exporter's, more pyramid levels than a camera
    image holds: one line each, before anything is written."""
    ck = make_checkpoint(tmp_path / "ck.pt", pose_head="points", pt_iters=(2, 2, 2))
    bad = torch.load(ck, weights_only=False)
    name = next(k for k, v in bad["model"].items() if v.is_floating_point())
    bad["model"][name] = torch.full_like(bad["model"][name], float("nan"))
    torch.save(bad, tmp_path / "nan.pt")
    for args, message in (([str(tmp_path / "nan.pt")], f"1 weight tensors hold NaN or inf (first: {name})"),
                          ([str(ck), "--opset", "24"], "--opset 24: torch"),
                          ([str(ck), "--set", "pt_iters=2,2,2,2,2,2"], "pt_iters: at most 5 pyramid levels, not 6")):
        r = runner.invoke(app, ["export", "--ckpt", *args, "--out", str(tmp_path / "o")])
        assert r.exit_code == 1 and message in r.output and "Traceback" not in r.output, (args, r.output)
        assert not (tmp_path / "o").exists()


def test_dynamic_batch(tmp_path):
    ck, cfg = _ckpt(tmp_path, **LEAN)
    export_checkpoint(ck, ExportConfig(out=tmp_path / "onnx", dynamic_batch=True))
    sm = StageModel(tmp_path / "onnx")
    rgb = np.random.rand(3, 3, 64, 224).astype(np.float32)
    depth = np.zeros((3, 1, 64, 224), np.float32)
    enc = sm.encode(rgb, sm.complete(rgb, depth), depth)
    assert enc and all(v.shape[0] == 3 for v in enc.values())
    camera = {"intrinsics": np.tile([[130.0, 130.0, 111.5, 31.5]], (3, 1)), "init_pose": np.tile(np.eye(4), (3, 1, 1))}
    assert sm.flow_pose(enc, enc, camera)["matrix"].shape == (3, 4, 4)


@pytest.mark.slow
def test_parity_at_paper_resolution(tmp_path):
    """1216x352 as in the paper: the default config with one Gauss-Newton step per level instead of
    four (each step is the same graph; the export takes a third less), on real frames when present."""
    torch.manual_seed(0)
    cfg = D3LVOConfig(gn_iters=1)
    save_checkpoint(tmp_path / "full.pt", D3LVO(cfg).eval(), cfg, step=0)
    export_checkpoint(tmp_path / "full.pt", ExportConfig(out=tmp_path / "onnx"))
    rep = run_parity(tmp_path / "full.pt", tmp_path / "onnx", frames=2)
    assert rep.passed, rep.to_dict()


def test_tampered_and_mismatched(exported, small_synth, tmp_path):
    ck, out, _ = exported
    stages = load_manifest(out)["stages"]
    assert set(stages) == {"completion", "encoder", "flowpose"}
    # every file the manifest lists is checked, not only one: onnxruntime's own flow+pose graph too
    files = graph_files(load_manifest(out))
    assert stages["flowpose"]["onnxruntime"]["file"] in files
    for file in files:
        bad = tmp_path / f"bad_{file}"
        shutil.copytree(out, bad)
        with open(bad / file, "ab") as fh:
            fh.write(b"\0")
        with pytest.raises(D3LVOInputError, match=f"{file}.*sha256"):
            StageModel(bad)
        (bad / file).unlink()
        with pytest.raises(D3LVOInputError, match=f"{file}.*missing"):
            StageModel(bad)
    bad = tmp_path / "no_hash"
    shutil.copytree(out, bad)
    m = json.loads((bad / "manifest.json").read_text())
    del m["stages"]["flowpose"]["sha256"]
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(D3LVOInputError, match="flowpose.*no sha256"):
        StageModel(bad)
    m = json.loads((out / "manifest.json").read_text())
    del m["model_config"]  # a hand-edited manifest: one line naming the key, not a KeyError later
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(D3LVOInputError, match="manifest.json: has no 'model_config'"):
        StageModel(bad)
    # an entry of model_config the runtime reads, damaged: one line naming it when the folder is
    # opened, before a run writes anything (else a TypeError or KeyError at the first frame)
    m = json.loads((out / "manifest.json").read_text())
    h, w = m["input"]["height"], m["input"]["width"]
    for key, value, words in (("height", str(h), f"model_config 'height' is '{h}', it must be a whole number"),
                              ("width", None, "model_config has no 'width'"),
                              ("height", h + 8, f"model_config 'height' is {h + 8}, its 'input' height {h}"),
                              ("rgb_std", 0.2, "model_config 'rgb_std' is 0.2, it must be a list of three numbers"),
                              ("rgb_mean", [0.5], "model_config 'rgb_mean' is [0.5], it must be a list of three numbers"),
                              ("max_depth", "far", "model_config 'max_depth' is 'far', it must be a finite number")):
        cfg = dict(m["model_config"], **{key: value})
        if value is None:
            del cfg[key]
        (bad / "manifest.json").write_text(json.dumps({**m, "model_config": cfg}))
        with pytest.raises(D3LVOInputError, match=f"manifest.json: {re.escape(words)}"):
            StageModel(bad)
    both = {**m, "input": {**m["input"], "width": w + 32}, "model_config": {**m["model_config"], "width": w + 32}}
    (bad / "manifest.json").write_text(json.dumps(both))
    with pytest.raises(D3LVOInputError, match=f"'input' is {w + 32}x{h}, the encoder's graph takes {w}x{h}"):
        StageModel(bad)
    r = runner.invoke(app, ["run", str(small_synth), "--onnx", str(bad), "--out", str(tmp_path / "damaged.txt")])
    assert r.exit_code == 1 and "manifest.json" in r.output and "Traceback" not in r.output, r.output
    assert not list(tmp_path.glob("damaged.txt*"))  # nothing written
    other, _ = _ckpt(tmp_path, name="other.pt", mode="rgb")
    with pytest.raises(D3LVOInputError, match="another model config"):
        run_parity(other, out, frames=2)
    old = tmp_path / "old"  # a folder from before the inverse-depth stage interface
    shutil.copytree(out, old)
    m = json.loads((old / "manifest.json").read_text())
    (old / "manifest.json").write_text(json.dumps({**m, "version": 1}))
    with pytest.raises(D3LVOInputError, match="manifest version 1.*re-export"):
        StageModel(old)


def test_dense_depth_in_metres_by_hand(exported):
    _, out, _ = exported
    sm = StageModel(out)
    min_d = sm.config["min_depth"]
    inv = np.array([[1.0, 0.0, 0.25, min_d / 120.0]], np.float32)
    np.testing.assert_allclose(sm.dense_depth_m(inv), [[min_d, 0.0, 4 * min_d, 120.0]], rtol=1e-6)


def test_cli_export_errors(tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not torch")
    r = runner.invoke(app, ["export", "--ckpt", str(junk), "--out", str(tmp_path / "o")])
    assert r.exit_code == 1 and "not a PyTorch checkpoint" in r.output
    ck, _ = _ckpt(tmp_path)
    blocker = tmp_path / "file"
    blocker.write_text("")
    r = runner.invoke(app, ["export", "--ckpt", str(ck), "--out", str(blocker / "sub")])
    assert r.exit_code == 1 and "cannot write the folder for the exported graphs" in r.output and "Traceback" not in r.output
    r = runner.invoke(app, ["export", "--ckpt", str(ck), "--out", str(blocker)])
    assert r.exit_code == 1 and "is a file; --out names the folder" in r.output, r.output
    r = runner.invoke(app, ["export", "--ckpt", str(ck), "--out", str(tmp_path / "o"), "--set", "pt_damping=-5"])
    assert r.exit_code == 1 and "pt_damping must be 0 or more" in r.output and "Traceback" not in r.output, r.output
    r = runner.invoke(app, ["export", "--ckpt", str(ck), "--out", str(tmp_path / "o"), "--height", "100"])
    assert r.exit_code == 1 and "divisible by 16" in r.output
    r = runner.invoke(app, ["export", "--ckpt", str(ck), "--out", str(tmp_path / "o"), "--height", "0", "--width", "0"])
    assert r.exit_code == 1 and "input 0x0 is too small: at least 32x32" in r.output, r.output
    r = runner.invoke(app, ["export", "--ckpt", str(ck), "--out", str(tmp_path / "o"), "--calib-seq", str(tmp_path)])
    assert r.exit_code == 1 and "--calib-seq calibrates an INT8 export" in r.output, r.output
    assert not (tmp_path / "o").exists()
    r = runner.invoke(app, ["export", "--ckpt", str(tmp_path), "--out", str(tmp_path / "o")])
    assert r.exit_code == 1 and "is a folder, not a checkpoint file" in r.output


def test_cli_parity_json(exported, small_synth):
    """--backend auto checks the engine `d3lvo run` would take, and says which by name."""
    from d3lvo_deploy.backends import SessionConfig

    ck, out, _ = exported
    r = runner.invoke(app, ["parity", "--ckpt", str(ck), "--onnx", str(out), "--seq-dir", str(small_synth), "--json",
                            "--backend", "auto"])
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data["pass"] is True and data["chained"]["translation_m"] < 1e-4
    assert data["backend"] == SessionConfig(backend="auto").resolved().backend


# Bounds against the fp32 folder, per output, on the inputs each stage really gets (the fp32
# upstream stages' outputs on the frames): fp16 relative to the output's largest magnitude,
# int8 a fraction of the output's spread (max - min), so an output stuck at zero or at a
# constant cannot pass (its error is at least half the spread). The confidences are the
# solver's per-point weights, whose common scale cancels in the Gauss-Newton step: what they
# change for the pose is their relative error. A barely trained confidence is ~1 everywhere with
# a spread of 1e-3, under one INT8 step of a [0, 1] output (1/255), so a spread bound would test
# the CPU's rounding (AVX2 kernels err by 0.003, AVX-512 VNNI ones by less), not the export;
# 1 % of the weight is 2.5 INT8 steps, and a calibration off by 10x misses it.
FP16_REL = 1e-3
INT8_SPREAD = 0.1
INT8_WEIGHT_REL = 0.01


def _stage_inputs(model_dir, seq_dir, frames: int = 3) -> dict[str, list[dict]]:
    """What each stage receives on the first frames, built here from the frames and the fp32
    stages (not with export.quantize's calibration code, which a test of it must not trust)."""
    from d3lvo_deploy.frames import FramePreprocessor
    from d3lvo_deploy.onnx_model import camera_inputs, flowpose_feeds
    from d3lvo_deploy.sequence import KittiSequence

    m, seq = StageModel(model_dir), KittiSequence.open(seq_dir)
    h, w = seq.image(0).shape[:2]
    pre = FramePreprocessor.for_model(seq.calib, w, h, m.config, m.depth_input)
    feeds: dict[str, list[dict]] = {"completion": [], "encoder": [], "flowpose": []}
    prev = None
    for i in range(frames):
        rgb, sparse = pre.rgb_input(seq.image(i)), pre.invdepth_input(seq.scan(i))
        feeds["completion"].append({"rgb_norm": rgb, "sparse_invdepth": sparse})
        enc_in = {"rgb_norm": rgb, "invdepth": m.complete(rgb, sparse), "sparse_invdepth": sparse}
        feeds["encoder"].append(enc_in)
        enc = m.run("encoder", enc_in)
        if prev is not None:
            feeds["flowpose"].append(flowpose_feeds(m.input_names("flowpose"), prev, enc, camera_inputs(pre.K)))
        prev = enc
    return feeds


def _quantized_errors(fp32_dir, q_dir, seq_dir) -> dict[str, tuple[float, float, float]]:
    """(max |q - fp32|, max |fp32|, spread of fp32) per stage output."""
    f32, q = StageModel(fp32_dir), StageModel(q_dir)
    errs: dict[str, list] = {}
    for stage, items in _stage_inputs(fp32_dir, seq_dir).items():
        for fd in items:
            ref, got = f32.run(stage, fd), q.run(stage, fd)
            for k, r in ref.items():
                e = errs.setdefault(f"{stage}/{k}", [0.0, 0.0, np.inf, -np.inf])
                e[0] = max(e[0], float(np.abs(got[k].astype(np.float64) - r).max()))
                e[1] = max(e[1], float(np.abs(r).max()))
                e[2], e[3] = min(e[2], float(r.min())), max(e[3], float(r.max()))
    return {k: (e[0], e[1], e[3] - e[2]) for k, e in errs.items()}


@pytest.mark.parametrize("precision", ["fp16", "int8"])
def test_reduced_precision_exports(small_model, small_synth, tmp_path, precision):
    from d3lvo_deploy.geometry import relative, rotation_angle_precise
    from d3lvo_deploy.pipeline import RunConfig, run_sequence
    from d3lvo_deploy.poses import read_poses
    from d3lvo_deploy.sequence import KittiSequence

    _, fp32_dir = small_model
    out = tmp_path / precision
    # the fp32 folder exported before, converted as it is (`--onnx`; `--ckpt` with --precision
    # exports, then ends in the same conversion: test_train_config_file_round_trips_through_checkpoint_and_export)
    r = runner.invoke(app, ["export", "--onnx", str(fp32_dir), "--out", str(out), "--precision", precision,
                            *(["--calib-seq", str(small_synth)] if precision == "int8" else [])])
    assert r.exit_code == 0, r.output
    m = load_manifest(out)
    assert m["precision"] == precision
    ops = set()
    for st in m["stages"].values():
        model = onnx.load(str(out / st["file"]))
        assert non_standard_nodes(model) == []
        ops |= {n.op_type for n in model.graph.node}
        # fp16 keeps the Gauss-Newton flow+pose stage in fp32 (its solver overflows fp16)
        expect = "fp32" if precision == "fp16" and st["file"] == "flowpose.onnx" else precision
        assert {p.key: p.value for p in model.metadata_props}["d3lvo_precision"] == expect == st["precision"]
    if precision == "int8":
        assert {"QuantizeLinear", "DequantizeLinear"} <= ops
    else:
        assert "Cast" in ops
    errs = _quantized_errors(fp32_dir, out, small_synth)
    assert {k.split("/")[0] for k in errs} == set(m["stages"])
    bad = []
    for name, (err, mag, spread) in errs.items():
        print(f"{precision} {name}: max err {err:.3g}, |fp32| {mag:.3g}, spread {spread:.3g}")
        if name.startswith("flowpose/") and not any(k in name for k in ("flow_l", "confidence")):
            continue  # poses: checked below against the fp32 trajectory, in metres and degrees
        if precision == "fp16":
            bound = FP16_REL * mag
        else:
            bound = INT8_WEIGHT_REL * mag if "confidence" in name else INT8_SPREAD * spread
        if err > bound:
            bad.append(name)
    assert not bad, bad
    # the trajectory against fp32's, as a user sees it
    seq = KittiSequence.open(small_synth)
    run_sequence(seq, out, RunConfig(out=tmp_path / "p.txt"))
    run_sequence(seq, fp32_dir, RunConfig(out=tmp_path / "ref.txt"))
    est, ref = read_poses(tmp_path / "p.txt").poses, read_poses(tmp_path / "ref.txt").poses
    E = relative(ref, est)
    path = float(np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1).sum())
    t_err = float(np.linalg.norm(E[:, :3, 3], axis=1).max())
    r_err = float(np.degrees(rotation_angle_precise(E[:, :3, :3])).max())
    bound_t = 1e-3 if precision == "fp16" else 0.05  # fraction of the path length
    assert t_err <= bound_t * path and r_err <= (0.05 if precision == "fp16" else 1.0), (t_err, path, r_err)


def test_export_and_bench_load_no_engine_before_exporting():
    """`d3lvo export` and `d3lvo bench --ckpt` trace their graphs before any engine is loaded:
    importing their commands and the exporter, in a fresh process, loads neither onnxruntime nor
    OpenVINO (once either pybind11 module is in a process, torch's exporter traces ~1.5x slower,
    docs/export-and-parity.md)."""
    import subprocess
    import sys

    from conftest import ROOT

    code = ("import sys, cli.main, cli.export_cmd, cli.bench_cmd, export.onnx_export, d3lvo_deploy.bench; "
            "print(sorted(m for m in ('onnxruntime', 'openvino') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "[]", r.stdout
