"""The light net (conf/model/odmvnet_lite.yaml), distillation (distill_from=RUN) and the int8
export."""

import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from helpers import compose_config, predicted_depth, tiny_overrides
from hydra.utils import instantiate

from odmv.config import compose_train, model_configs
from odmv.data.dataset import SampleSpec, load_scene
from odmv.deploy.export import export
from odmv.deploy.onnx import METADATA_KEY
from odmv.deploy.quantize import INT8_OPS
from odmv.io.manifest import load_manifest
from odmv.models import ODMVNet, count_parameters
from odmv.models.blocks import SeparableConv3d, set_separable
from odmv.study.graphs import main as graphs_main
from odmv.training.module import load_module
from odmv.training.run import train

DOCS = Path(__file__).resolve().parents[1] / "docs"
LIGHT = [n for n, c in model_configs().items() if c.get("model", {}).get("max_parameters")]


@pytest.mark.parametrize("name", LIGHT)
@pytest.mark.parametrize("protocol", ["paper", "mini"])
def test_every_light_net_fits_its_parameter_budget(name, protocol):
    for head in ("depth", "phase"):
        cfg = compose_train([f"experiment={protocol}", f"model={name}", f"head={head}"])
        with torch.device("meta"):
            n = count_parameters(instantiate(cfg.model.net, _convert_="all"))
        assert n <= cfg.model.max_parameters, n


def test_separable_convolutions_put_the_depthwise_part_on_the_narrow_side():
    torch.manual_seed(0)
    net = torch.nn.Sequential(
        torch.nn.Conv3d(8, 16, 3, padding=1),
        torch.nn.Conv3d(16, 8, 3, padding=1),
        torch.nn.Conv3d(2, 1, (3, 7, 7), padding=(1, 3, 3)),  # too few channels to factor
    )
    full = count_parameters(net)
    set_separable(net, True)
    grow, shrink = net[0], net[1]
    assert isinstance(grow, SeparableConv3d) and isinstance(shrink, SeparableConv3d)
    assert (grow[0].groups, grow[0].kernel_size, grow[1].kernel_size) == (8, (3, 3, 3), (1, 1, 1))
    assert (shrink[0].kernel_size, shrink[1].groups) == ((1, 1, 1), 8)
    assert type(net[2]) is torch.nn.Conv3d
    assert count_parameters(net) < full / 5
    assert net[:2](torch.rand(1, 8, 4, 16, 16)).shape == (1, 8, 4, 16, 16)


def test_the_quarter_resolution_backbone_takes_480_px_multiples():
    net = ODMVNet(base_width=4, blocks=1, stem_stride=4, levels=3, separable=True, full_width=4)
    out = net(torch.rand(1, 4, 96, 64) * 2 - 1)  # multiples of 4 x 2^3 = 32
    assert out["depth"].shape == (1, 1, 96, 64) and [a.shape[-1] for a in out["aux"]] == [16, 8]
    assert [m.shape[-1] for m in out["occlusion"]] == [16, 8, 4]
    with pytest.raises(ValueError, match="divisible by 32"):
        net(torch.rand(1, 4, 80, 64))
    with pytest.raises(ValueError, match="stem_stride 3"):
        ODMVNet(base_width=4, stem_stride=3)


@pytest.fixture(scope="module")
def teacher(tiny_dataset, tmp_path_factory):
    """A tiny full ODMV-Net with the phase head, trained one epoch: its run folder."""
    out = tmp_path_factory.mktemp("teacher")
    ov = tiny_overrides(tiny_dataset, out, "widths.odmvnet=4", "head=phase", "reference=true")
    train(compose_config("train", [*ov, "data.fringe_frequency=1"]))
    return out


def _student(tiny_dataset, out, teacher, *extra):
    ov = tiny_overrides(tiny_dataset, out, "model=odmvnet_lite", "widths.odmvnet_lite=4")
    ov += ["head=phase", "reference=true", "data.fringe_frequency=1", f"distill_from={teacher}"]
    return compose_config("train", [o for o in ov if o != "model.net.base_width=4"] + list(extra))


@pytest.mark.slow
def test_the_light_net_distils_exports_as_float32_and_int8_and_predicts(
    teacher, tiny_dataset, tmp_path, capsys
):
    metrics = train(_student(tiny_dataset, tmp_path / "run", teacher))
    student = load_module(metrics["best_checkpoint"])
    assert str(teacher) in student.hparams.distill["teacher"]
    assert student.hparams.net_cfg["separable"] and student.hparams.net_cfg["stem_stride"] == 4
    header, *rows = (tmp_path / "run" / "csv" / "metrics.csv").read_text().splitlines()
    names = header.split(",")
    for term in ("distill_depth", "distill_phase", "distill_confidence"):
        column = [r.split(",")[names.index(f"train/loss_{term}")] for r in rows]
        assert [float(v) for v in column if v] and all(float(v) >= 0 for v in column if v)

    cfg = compose_config(
        "export",
        [f"ckpt_path={metrics['best_checkpoint']}", f"out={tmp_path / 'onnx'}", "check_scenes=2"]
        + ["precisions=[float32,int8]", "int8_keep_float=1"],
    )
    export(cfg)
    scene = tiny_dataset / "scenes" / "000004"
    depth = {}
    for precision in ("float32", "int8"):
        name = "model.onnx" if precision == "float32" else f"model.{precision}.onnx"
        path = tmp_path / "onnx" / name
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        meta = json.loads(session.get_modelmeta().custom_metadata_map[METADATA_KEY])
        assert meta["precision"] == precision and meta["views"] == student.hparams.views
        if precision == "int8":  # the convolution int8 costs most stays float32, the rest not
            graph = onnx.load(str(path)).graph
            made_by = {out: node.op_type for node in graph.node for out in node.output}
            convs = [n for n in graph.node if n.op_type in INT8_OPS]
            quantized = [n.name for n in convs if made_by.get(n.input[1]) == "DequantizeLinear"]
            kept = meta["float32_convolutions"]
            assert len(kept) == 1 and kept[0] in {n.name for n in convs} - set(quantized)
            assert quantized
        depth[precision] = predicted_depth(path, scene, tmp_path / precision)
    assert np.isfinite(depth["int8"]).all() and np.abs(depth["int8"] - depth["float32"]).mean() < 2

    # the graphs scored on the test split: float32 as PyTorch, int8 beside it
    capsys.readouterr()
    assert graphs_main([metrics["best_checkpoint"], "--out", str(tmp_path / "graphs")]) == 0
    row = capsys.readouterr().out.splitlines()[-1].split("|")
    pytorch, float32, int8 = (float(row[k]) for k in (2, 3, 4))
    assert float32 == pytest.approx(pytorch, abs=1e-4) and np.isfinite(int8)
    assert pytorch == pytest.approx(metrics["test/mae_mm"], rel=1e-4)

    # docs/deploy.md's consumer (ONNX Runtime and numpy) gives predict's depth
    doc = (DOCS / "deploy.md").read_text().split("A consumer: ONNX Runtime and numpy")[1]
    code = doc.split("```python\n")[1].split("```")[0]
    space = {}
    exec(compile(code, "docs/deploy.md", "exec"), space)
    views = list(student.hparams.views)
    spec = SampleSpec(tuple(views), 32, 32, 1, student.hparams.input_spec["step"])
    frames = load_scene(load_manifest(tiny_dataset), "000004", spec)["fringes"]
    got = space["depth_mm"](frames, str(tmp_path / "onnx"))
    np.testing.assert_allclose(got, depth["float32"], atol=1e-3)


def test_a_teacher_that_reads_other_views_is_refused(teacher, tiny_dataset, tmp_path):
    with pytest.raises(ValueError, match="teacher's views"):
        train(_student(tiny_dataset, tmp_path, teacher, "views=2"))
