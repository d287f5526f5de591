"""An int8 copy of an exported graph (``python -m odmv.export precisions=[float32,int8]``):
ONNX Runtime's static quantization of the convolutions (QDQ, weights int8 per output channel,
activations uint8), its activation ranges calibrated on the run's own training scenes, checked
against the float32 graph in mm on the run's validation scenes (test scenes where it has none),
carrying the same ``odmv`` metadata so predict and any consumer run it like the float32 file.

Whether it pays depends on the runtime's kernels: ONNX Runtime 1.32 on this 2-core x86 CPU runs
the light net's int8 graph 7x slower than float32, and its error rises by half
(docs/deploy.md). float16 is not offered for the CPU: that runtime has no float16 convolution
there (a converted graph ran no faster, 92 against 90 ms, and an autocast export failed in its
float16 Conv kernel).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from odmv.deploy.onnx import METADATA_KEY
from odmv.io.atomic import write_atomic
from odmv.training.evaluation import checkpoint_datamodule
from odmv.training.module import batched, load_module, net_input

PRECISIONS = ("float32", "int8")
#: what int8 quantizes: the convolutions; fusion, triangulation and the mm output stay float32
#: (the light net, seed 0, test split: 0.3648 mm against 0.4470 with every operator quantized;
#: float32 0.2448)
INT8_OPS = ("Conv", "ConvTranspose")


def scene_feeds(ckpt_path: str | Path, n: int) -> dict[str, list[dict]]:
    """The graph's inputs for up to ``n`` scenes of the run's dataset (read as the run read
    it): ``check`` from its validation split (else test), ``calibration`` from its training
    split."""
    module = load_module(ckpt_path).eval()
    dm = checkpoint_datamodule(module, None, augment=None)
    feeds = {}
    for use, splits in (("check", ("val", "test")), ("calibration", ("train",))):
        split = next((s for s in splits if len(dm.datasets.get(s) or ())), None)
        if split is None:
            raise ValueError(f"{ckpt_path}: its dataset holds no {' or '.join(splits)} scenes")
        ds = dm.datasets[split]
        feeds[use] = []
        for i in range(min(n, len(ds))):
            sample = batched(ds[i])
            feed = {"inputs": net_input(sample).numpy()}
            if module.phase_head:
                feed["calibration"] = sample["calibration"].numpy()
            feeds[use].append(feed)
    return feeds


def _with_metadata(model, source, precision: str, kept: list[str]):
    """``model`` with ``source``'s odmv metadata, its precision and the convolutions it kept
    float32 added."""
    meta = json.loads(next(p.value for p in source.metadata_props if p.key == METADATA_KEY))
    del model.metadata_props[:]
    entry = model.metadata_props.add()
    meta |= {"precision": precision, "float32_convolutions": kept}
    entry.key, entry.value = METADATA_KEY, json.dumps(meta)
    return model


def int8_model(path: Path, feeds: list[dict], keep_float=()):
    """``path`` (a float32 graph) statically quantized to int8, calibrated on ``feeds``; the
    convolutions named in ``keep_float`` stay float32."""
    with tempfile.TemporaryDirectory(prefix="odmv-int8-") as tmp:
        return _quantized(_prepared(path, Path(tmp)), feeds, keep_float)


def _prepared(path: Path, tmp: Path) -> Path:
    """``path`` through the quantizer's shape inference and graph clean-up."""
    from onnxruntime.quantization.shape_inference import quant_pre_process

    prepared = tmp / "prepared.onnx"
    # the exporter's dynamic batch leaves symbolic shapes the symbolic pass cannot finish
    quant_pre_process(str(path), str(prepared), skip_symbolic_shape=True)
    return prepared


def _quantized(prepared: Path, feeds: list[dict], keep_float=(), only=None):
    """A prepared graph (:func:`_prepared`) quantized as :func:`int8_model` says; ``only``:
    quantize those convolutions alone."""
    import onnx
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.left = iter(feeds)

        def get_next(self):
            return next(self.left, None)

    with tempfile.TemporaryDirectory(prefix="odmv-int8-") as tmp:
        quantized = Path(tmp, "int8.onnx")
        quantize_static(
            str(prepared),
            str(quantized),
            Reader(),
            quant_format=QuantFormat.QDQ,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            per_channel=True,
            op_types_to_quantize=list(INT8_OPS),
            nodes_to_quantize=list(only) if only is not None else None,
            nodes_to_exclude=list(keep_float),
        )
        return onnx.load(str(quantized))


def conv_sensitivity(path: Path, feeds: dict[str, list[dict]]) -> dict[str, float]:
    """Each convolution's cost of int8 alone: the mean |depth difference| (mm) from the
    float32 graph ``path`` on ``feeds["check"]`` with that convolution quantized and nothing
    else (calibrated on ``feeds["calibration"]``), largest first."""
    import onnx

    with tempfile.TemporaryDirectory(prefix="odmv-int8-") as tmp:
        prepared = _prepared(path, Path(tmp))  # once: every quantization starts from it
        graph = onnx.load(str(prepared)).graph
        names = [n.name for n in graph.node if n.op_type in INT8_OPS]
        cost = {}
        for name in names:
            one = Path(tmp, "one.onnx")
            onnx.save(_quantized(prepared, feeds["calibration"], only=[name]), str(one))
            cost[name] = depth_difference_mm(path, one, feeds["check"])[0]
    return dict(sorted(cost.items(), key=lambda kv: -kv[1]))


def depth_difference_mm(reference: Path, other: Path, feeds: list[dict]) -> tuple[float, float]:
    """Mean and largest |depth(other) - depth(reference)| (mm) over ``feeds``."""
    import onnxruntime as ort

    cpu = ["CPUExecutionProvider"]
    ref, new = (ort.InferenceSession(str(p), providers=cpu) for p in (reference, other))
    diffs = [np.abs(new.run(None, f)[0] - ref.run(None, f)[0]) for f in feeds]
    return float(np.mean([d.mean() for d in diffs])), float(max(d.max() for d in diffs))


def check_precisions(precisions) -> None:
    unknown = [p for p in precisions if p not in PRECISIONS]
    if unknown:
        raise ValueError(f"precisions: {unknown} unknown; choose from {list(PRECISIONS)}")


def export_precisions(
    ckpt_path: str | Path, float32_path: Path, precisions, scenes: int = 16, keep_float: int = 0
) -> dict[str, tuple[Path, float, float]]:
    """Write ``model.int8.onnx`` beside the float32 graph where ``precisions`` name int8, its
    ``keep_float`` convolutions that int8 costs most (:func:`conv_sensitivity`) left float32;
    returns {precision: (path, mean mm, max mm against float32)} of what it wrote."""
    import onnx

    check_precisions(precisions)
    if "int8" not in precisions:
        return {}
    if keep_float < 0:
        raise ValueError(f"int8_keep_float: {keep_float}: a count of convolutions, 0 or more")
    feeds = scene_feeds(ckpt_path, scenes)
    kept = list(conv_sensitivity(float32_path, feeds))[:keep_float] if keep_float else []
    model = int8_model(float32_path, feeds["calibration"], keep_float=kept)
    model = _with_metadata(model, onnx.load(str(float32_path)), "int8", kept)
    path = float32_path.with_name("model.int8.onnx")
    write_atomic(path, lambda tmp: onnx.save(model, str(tmp)))
    return {"int8": (path, *depth_difference_mm(float32_path, path, feeds["check"]))}
