"""ONNX export: the exported graph gives the checkpoint's depth, and predict runs it."""

import json

import numpy as np
import onnxruntime as ort
import pytest
import torch
from helpers import compose_config, tiny_overrides

from odmv.deploy.onnx import METADATA_KEY, export_onnx
from odmv.deploy.predict import predict
from odmv.io.exr import read_channel
from odmv.training.module import load_module
from odmv.training.run import train


@pytest.fixture(scope="module")
def trained_unet(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("unet")
    overrides = [o for o in tiny_overrides(tiny_dataset, out) if not o.startswith("model.net.")]
    cfg = compose_config(
        "train", [*overrides, "model=unet", "widths.unet=4", "views=2", "reference=true"]
    )
    return train(cfg)["best_checkpoint"]


@pytest.mark.parametrize("which", ["odmvnet", "unet"])
def test_onnx_depth_matches_pytorch_and_predict_runs_it(
    which, trained, trained_unet, tiny_dataset, tmp_path
):
    ckpt = trained[1]["best_checkpoint"] if which == "odmvnet" else trained_unet
    path, diff = export_onnx(ckpt, tmp_path / "export")
    assert path == tmp_path / "export" / "model.onnx" and diff < 1e-3
    module = load_module(ckpt).eval()
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    meta = json.loads(session.get_modelmeta().custom_metadata_map[METADATA_KEY])
    assert meta["views"] == list(module.hparams.views) and meta["input_size"] == [32, 32]
    assert meta["norm"] == dict(module.hparams.norm)
    # a batch of three real inputs: the dynamic batch axis, depth in mm within 1e-3 mm
    x = torch.randn(3, meta["in_channels"], 32, 32)
    with torch.no_grad():
        ref = module.depth_mm(module(x)).numpy()
    got = session.run(None, {"inputs": x.numpy()})[0]
    assert got.shape == (3, 1, 32, 32) and np.abs(got - ref).max() < 1e-3

    scene = tiny_dataset / "scenes" / "000004"
    depths = {}
    for name, model in (("ckpt", ckpt), ("onnx", path)):
        cfg = compose_config(
            "predict",
            [
                f"ckpt_path={model}",
                f"input={scene}",
                f"out={tmp_path / name}",
                f"paths.output_dir={tmp_path}",
            ],
        )
        depths[name] = read_channel(predict(cfg)[0]["depth"], "Z")
    assert np.abs(depths["onnx"] - depths["ckpt"]).max() < 1e-3
    assert 100 < np.median(depths["onnx"]) < 200
