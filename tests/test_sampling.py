"""The Gather form of bilinear sampling (onnxruntime's flow+pose graph) against GridSample and by hand."""

import json
import shutil

import numpy as np
import onnx
import pytest
import torch
import torch.nn.functional as F

from d3lvo_deploy.errors import D3LVOInputError
from d3lvo_deploy.manifest import for_engine, load_manifest
from d3lvo_deploy.onnx_model import SessionConfig, StageModel
from export.onnx_export import all_nodes
from models.sampling import (bilinear, bilinear_inside, gathered, gathering, grid_sample_channels, grid_sample_shared,
                             inside_lattice)


def _grid_sample(x, uv):
    """GridSample (zeros, align_corners) at pixel positions uv (B,2,N)."""
    h, w = x.shape[-2:]
    grid = torch.stack([2.0 * uv[:, 0] / (w - 1) - 1.0, 2.0 * uv[:, 1] / (h - 1) - 1.0], -1).unsqueeze(1)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=True)[:, :, 0]


def test_hand_computed_and_zeros_outside():
    x = torch.tensor([[[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]]])  # 2 rows, 3 columns
    uv = torch.tensor([[[0.0, 2.0, 0.5, 1.5, -0.5, 2.5, 1.0, -3.0], [0.0, 1.0, 0.5, 0.0, 0.0, 1.0, 1.5, 0.0]]])
    # corners; the mean of a cell; halfway along the top row; half a pixel beyond the left and the
    # right border and below the bottom (blended with zero); far outside (zero)
    want = [1.0, 6.0, 3.0, 2.5, 0.5, 3.0, 2.5, 0.0]
    assert bilinear(x, uv)[0, 0].tolist() == pytest.approx(want, abs=1e-6)


def test_matches_grid_sample_batched():
    torch.manual_seed(0)
    x = torch.rand(2, 5, 13, 21)
    uv = torch.rand(2, 2, 600) * torch.tensor([28.0, 20.0]).view(1, 2, 1) - 4.0  # inside, border band, outside
    uv[1, :, :4] = torch.tensor([[0.0, 20.0, 0.0, 20.0], [0.0, 12.0, 12.0, 0.0]])  # the four corners
    assert (bilinear(x, uv) - _grid_sample(x, uv)).abs().max() < 1e-5
    # inside the image (GridSample coordinates [-1, 1], borders included) the GatherElements form
    grid = torch.rand(2, 2, 600) * 2.0 - 1.0
    grid[0, :, :4] = torch.tensor([[1.0, -1.0, 1.0, -1.0], [1.0, -1.0, -1.0, 1.0]])
    ref = F.grid_sample(x, grid.transpose(1, 2).unsqueeze(1), mode="bilinear", padding_mode="zeros",
                        align_corners=True)[:, :, 0]
    assert (bilinear_inside(x, grid) - ref).abs().max() < 1e-6
    # with its lattice computed once, as the Gauss-Newton steps call it
    assert (bilinear_inside(x, grid, inside_lattice(x)) - ref).abs().max() < 1e-6


def test_solves_sharing_an_image():
    """Two solves per pair on one copy of its image (the weighted and the classical solve): batch
    rows 2i and 2i + 1 sample image i, as GridSample on the image repeated for each row does."""
    torch.manual_seed(1)
    x = torch.rand(2, 3, 11, 17)  # two pairs
    grid = torch.rand(4, 2, 300) * 2.0 - 1.0  # four solves
    copies = x.repeat_interleave(2, 0)
    ref = F.grid_sample(copies, grid.transpose(1, 2).unsqueeze(1), mode="bilinear", padding_mode="zeros",
                        align_corners=True)[:, :, 0]
    assert (bilinear_inside(x, grid, inside_lattice(x, grid)) - ref).abs().max() < 1e-6
    assert (grid_sample_shared(x, grid) - ref).abs().max() < 1e-6
    assert (grid_sample_shared(x, grid * 1.2) - _grid_sample(copies, (grid * 1.2 + 1.0) * torch.tensor(
        [8.0, 5.0]).view(1, 2, 1))).abs().max() < 1e-5  # zeros outside, as GridSample
    # with one solve per image it is GridSample itself
    assert (grid_sample_shared(copies, grid) - ref).abs().max() < 1e-6
    # split by channel (OpenVINO's solver steps): channel c of every row, shared image or copies
    for image in (x, copies):
        channels = grid_sample_channels(image, grid)
        assert len(channels) == 3 and all(c.shape == (4, 1, 300) for c in channels)
        assert (torch.cat(channels, 1) - ref).abs().max() < 1e-6


def test_gathered_is_scoped():
    assert not gathering()
    with gathered():
        assert gathering()
    assert not gathering()


def test_onnxruntime_graph_in_the_export(small_model, tmp_path):
    """The export writes the flow+pose stage twice: GridSample for OpenVINO, Gathers for
    onnxruntime; same inputs and outputs, same results, each engine opens its own."""
    import onnxruntime as ort  # here, not at import: see `_prebuilt` in conftest.py

    _, out = small_model
    m = load_manifest(out)
    st = m["stages"]["flowpose"]
    own = st["onnxruntime"]
    main_graph, own_graph = onnx.load(str(out / st["file"])), onnx.load(str(out / own["file"]))
    ops = lambda g: {n.op_type for n in all_nodes(g.graph)}  # noqa: E731
    assert "GridSample" in ops(main_graph) and "GridSample" not in ops(own_graph)
    assert "onnxruntime" not in m["stages"]["encoder"]  # no bilinear samples there
    feeds = {}
    rng = np.random.default_rng(0)
    for i in st["inputs"]:
        feeds[i["name"]] = rng.random([d if isinstance(d, int) else 1 for d in i["shape"]], dtype=np.float32)
    feeds["init_pose"] = np.eye(4, dtype=np.float32)[None] if "init_pose" in feeds else None
    feeds = {k: v for k, v in feeds.items() if v is not None}
    a = ort.InferenceSession(str(out / st["file"]), providers=["CPUExecutionProvider"]).run(None, feeds)
    b = ort.InferenceSession(str(out / own["file"]), providers=["CPUExecutionProvider"]).run(None, feeds)
    for o, x, y in zip(st["outputs"], a, b):
        assert np.abs(x - y).max() < 1e-4, o["name"]
    sm = StageModel(out, SessionConfig(backend="onnxruntime"))
    meta = sm.sessions["flowpose"].sess.get_modelmeta().custom_metadata_map
    assert meta.get("d3lvo_sampling") == "gather"
    assert for_engine(st, "openvino")["file"] == st["file"] and for_engine(st, "onnxruntime")["file"] == own["file"]
    # an entry without its hash is refused (a damaged or missing file: test_export's tamper test)
    bad = tmp_path / "bad"
    shutil.copytree(out, bad)
    mm = json.loads((out / "manifest.json").read_text())
    del mm["stages"]["flowpose"]["onnxruntime"]["sha256"]
    (bad / "manifest.json").write_text(json.dumps(mm))
    with pytest.raises(D3LVOInputError, match="onnxruntime graph has no file name or no sha256"):
        StageModel(bad)
