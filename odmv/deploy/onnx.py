"""A trained net as an ONNX graph (written by ``python -m odmv.export``).

Writes ``DIR/model.onnx``: input ``inputs`` (batch x channels x H x W, the net's input as the
data module builds it: normalized fringes, plus the reference phase where the net was trained
with it), output ``depth_mm`` (batch x 1 x H x W, camera-axis depth in mm: the normalization is
inside the graph). A net with the phase head (``head=phase``) takes a second input,
``calibration`` (batch x S x 6 x H x W, the rig's triangulation maps of
odmv.classical.geometry), and
gives a second output, ``weights`` (batch x (S + 1) x H x W, each view's share of the fused
depth, then the regressed depth's). The calibration is an input, not constants in the graph,
so a re-calibrated rig (or a second rig of the same design) runs the same file: the predictor
builds the maps from ``calibration=FILE`` as it builds the reference phase. The batch is
dynamic; H and W are the training size. The metadata entry ``odmv`` (JSON) holds what
:func:`odmv.deploy.inference.load_predictor` needs to build the input from images: views in order,
input size, normalization and input settings. A net whose run was calibrated (odmv.study
uncertainty) gives a last output, ``score_mm`` (batch x 1 x H x W, its uncertainty score), and
its calibration is in the metadata (``error_bars``): predict turns the score into intervals.
"""

from __future__ import annotations

import copy
import json
import logging
import warnings
from pathlib import Path

import numpy as np
import torch

from odmv.classical.geometry import triangulation_maps
from odmv.data.reference import view_channels
from odmv.io.atomic import write_atomic
from odmv.models.blocks import fold_batchnorm
from odmv.rig import Rig, size_hw
from odmv.training.module import FPPModule, load_module
from odmv.training.uncertainty import calibration_of, pixel_score

#: ONNX opset: Conv and ConvTranspose in 3D and 5D linear Resize (trilinear) are all covered.
OPSET = 18
METADATA_KEY = "odmv"


class DepthInMM(torch.nn.Module):
    """The net plus its output normalization: inputs (and calibration maps, for the phase
    head) -> depth in mm (float32) (and the fusion's weights)."""

    def __init__(self, module: FPPModule, score: str | None = None):
        super().__init__()
        self.module = module
        self.score = score  # a calibrated net's uncertainty score, a third output

    def forward(self, inputs: torch.Tensor, calibration: torch.Tensor | None = None):
        out = self.module(inputs, calibration)
        depth = self.module.norm.depth_mm(out["depth"].float())
        outputs = [depth] + ([out["weights"]] if calibration is not None else [])
        if self.score is not None:
            outputs.append(pixel_score(out, depth, self.score))
        return outputs[0] if len(outputs) == 1 else tuple(outputs)


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


def export_graph(model: torch.nn.Module, example: torch.Tensor, maps: torch.Tensor | None = None):
    """The ONNX ModelProto of ``model`` (input ``inputs`` with a dynamic batch, output
    ``depth_mm``; with ``maps`` also the input ``calibration`` and the output ``weights``),
    traced with ``example`` from a copy with its BatchNorms folded into the convolutions
    (:func:`~odmv.models.blocks.fold_batchnorm`); the exporter's chatter silenced."""
    model = fold_batchnorm(copy.deepcopy(model).eval())
    for name in ("torch.onnx", "onnxscript", "onnx_ir"):  # notes on its own passes
        logging.getLogger(name).setLevel(logging.ERROR)
    batch = torch.export.Dim("batch", min=1, max=1024)
    args, names, shapes = (example,), ["inputs"], {"inputs": {0: batch}}
    if maps is not None:
        args, names = (example, maps), ["inputs", "calibration"]
        shapes["calibration"] = {0: batch}
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(
            model,
            args,
            input_names=names,
            output_names=["depth_mm"]
            + (["weights"] if maps is not None else [])
            + (["score_mm"] if getattr(model, "score", None) else []),
            dynamic_shapes=shapes,
            opset_version=OPSET,
            dynamo=True,
            external_data=False,
            verbose=False,
        )
    return program.model_proto


def example_inputs(module: FPPModule) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Two random inputs of the net's shape (and, for the phase head, the twin's calibration
    maps at the input size: any rig's maps are valid input)."""
    channels, h, w = input_shape(module)
    example = torch.randn(2, channels, h, w)
    maps = None
    if module.phase_head:
        spec = module.hparams.input_spec
        one = triangulation_maps(
            Rig(), module.hparams.views, h, w, spec["period_px"], spec["step"], spec["n_steps"]
        )
        maps = torch.from_numpy(one)[None].expand(2, *one.shape).contiguous()
    return example, maps


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
    bars = calibration_of(Path(ckpt_path))  # a calibrated net carries its error bars
    wrapper = DepthInMM(module, bars["score"] if bars else None).eval()
    example, maps = example_inputs(module)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "model.onnx"
    model = export_graph(wrapper, example, maps)
    entry = model.metadata_props.add()
    meta = metadata(module, ckpt_path) | {"precision": "float32"}
    if bars:
        meta["error_bars"] = bars
    entry.key, entry.value = METADATA_KEY, json.dumps(meta)
    write_atomic(path, lambda tmp: onnx.save(model, str(tmp)))
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    feed = {"inputs": example.numpy()}
    with torch.no_grad():
        if maps is None:
            ref = wrapper(example)
        else:
            ref = wrapper(example, maps)
            feed["calibration"] = maps.numpy()
    ref = [ref] if torch.is_tensor(ref) else list(ref)
    got = session.run(None, feed)
    # depth and, where the graph gives it, the score (mm both); the weights are shares
    checked = [0] + ([len(got) - 1] if bars else [])
    return path, max(float(np.abs(got[k] - ref[k].numpy()).max()) for k in checked)
