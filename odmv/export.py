"""Export a trained net to ONNX: ``python -m odmv.export ckpt_path=CKPT out=DIR``.

Writes ``DIR/model.onnx``: input ``inputs`` (batch x channels x H x W, the net's input as the
data module builds it: normalized fringes, plus the reference phase where the net was trained
with it), output ``depth_mm`` (batch x 1 x H x W, camera-axis depth in mm: the normalization is
inside the graph). The batch is dynamic; H and W are the training size. The metadata entry
``odmv`` (JSON) holds what :func:`odmv.inference.load_predictor` needs to build the input from
images: views in order, input size, normalization and input settings.
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from odmv.cli import run_app
from odmv.config import CONF_DIR  # (and registers the config resolvers)
from odmv.data.reference import view_channels
from odmv.io.atomic import write_atomic
from odmv.module import FPPModule, load_module
from odmv.rig import size_hw

#: ONNX opset: Conv and ConvTranspose in 3D and 5D linear Resize (trilinear) are all covered.
OPSET = 18
METADATA_KEY = "odmv"


class DepthInMM(torch.nn.Module):
    """The net plus its output normalization: inputs -> depth in mm (float32)."""

    def __init__(self, module: FPPModule):
        super().__init__()
        self.net, self.norm = module.net, module.norm

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        return self.norm.depth_mm(self.net(inputs)["depth"].float())


def input_shape(module: FPPModule) -> tuple[int, int, int]:
    """(channels, H, W) of the net's input, from the checkpoint's settings."""
    h, w = size_hw((module.hparams.data_cfg or {}).get("resolution", 480))
    spec = module.hparams.input_spec or {}
    per_view = view_channels(spec.get("reference", False)) + bool(spec.get("availability"))
    in_channels = len(module.hparams.views) * per_view
    return in_channels, h, w


def metadata(module: FPPModule, ckpt_path: str | Path) -> dict:
    channels, h, w = input_shape(module)
    return {
        "views": list(module.hparams.views),
        "input_size": [h, w],
        "in_channels": channels,
        "norm": dict(module.hparams.norm),
        "input_spec": dict(module.hparams.input_spec or {}),
        "net": module.hparams.net_cfg.get("_target_"),
        "checkpoint": str(Path(ckpt_path).resolve()),
    }


def export_graph(model: torch.nn.Module, example: torch.Tensor):
    """The ONNX ModelProto of ``model`` (input ``inputs`` with a dynamic batch, output
    ``depth_mm``), traced with ``example``; the exporter's chatter silenced."""
    for name in ("torch.onnx", "onnxscript", "onnx_ir"):  # notes on its own passes
        logging.getLogger(name).setLevel(logging.ERROR)
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(
            model,
            (example,),
            input_names=["inputs"],
            output_names=["depth_mm"],
            dynamic_shapes={"inputs": {0: torch.export.Dim("batch", min=1, max=1024)}},
            opset_version=OPSET,
            dynamo=True,
            external_data=False,
            verbose=False,
        )
    return program.model_proto


def export_onnx(ckpt_path: str | Path, out_dir: str | Path) -> tuple[Path, float]:
    """Write ``out_dir/model.onnx``; returns its path and the largest difference (mm) between
    ONNX Runtime and PyTorch on two random inputs (a check, printed by the app)."""
    import onnx
    import onnxruntime as ort

    module = load_module(ckpt_path).eval()
    if module.norm is None or not module.hparams.views:
        raise ValueError(
            f"{ckpt_path}: the checkpoint has no normalization or views (not trained?)"
        )
    wrapper = DepthInMM(module).eval()
    channels, h, w = input_shape(module)
    example = torch.randn(2, channels, h, w)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "model.onnx"
    model = export_graph(wrapper, example)
    entry = model.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(metadata(module, ckpt_path))
    write_atomic(path, lambda tmp: onnx.save(model, str(tmp)))
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        ref = wrapper(example).numpy()
    got = session.run(None, {"inputs": example.numpy()})[0]
    return path, float(np.abs(got - ref).max())


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="export")
def main(cfg: DictConfig) -> None:
    path, diff = run_app(lambda: export_onnx(cfg.ckpt_path, cfg.out))
    print(f"{path}: ONNX Runtime matches PyTorch within {diff:.2e} mm")


if __name__ == "__main__":
    main()
