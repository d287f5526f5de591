"""A trained net as a depth function: a checkpoint (run by PyTorch) or an exported ONNX model
(run by ONNX Runtime) with the views, input size, normalization and input settings it was
trained with. Used by ``odmv.predict`` and by anything that runs a net on images. A net with
the phase head (``head=phase``) also takes the rig's triangulation maps
(odmv.classical.geometry), built
from the same calibration as the reference phase, and gives each view's fusion weight."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from odmv.classical.geometry import triangulation_maps
from odmv.data.normalize import Normalization
from odmv.data.reference import network_input, reference_mode, reference_phase
from odmv.data.views import with_availability
from odmv.deploy.onnx import METADATA_KEY, input_shape
from odmv.models.phase import check_head, reads_maps
from odmv.rig import Rig
from odmv.training.module import load_module
from odmv.training.uncertainty import calibration_of, pixel_score


@dataclass
class Predictor:
    """A trained net with what it needs to turn images into depth: its views in order, input
    size (H, W), normalization and input settings, and ``run``: (net input, calibration maps
    or None) -> {"depth_mm": B x 1 x H x W, and with the phase head "weights": B x (S + 1) x
    H x W, each view's share of the fused depth, then the regressed depth's}."""

    views: list[str]
    size: tuple[int, int]
    norm: Normalization
    input_spec: dict
    run: Callable[[torch.Tensor, torch.Tensor | None], dict]
    error_bars: dict | None = None  # its run's uncertainty.json (odmv.study.uncertainty)

    def factor(self, coverage: float) -> float:
        """The calibrated factor q at ``coverage`` (the interval is depth ± q x score)."""
        factors = self.error_bars["factor"]
        if str(coverage) not in factors:
            raise ValueError(f"coverage={coverage}: calibrated at {', '.join(factors)} only")
        return factors[str(coverage)]

    def half_width_mm(self, score: np.ndarray, coverage: float) -> np.ndarray:
        """Each pixel's interval half width (mm) at ``coverage`` from its score."""
        return (self.factor(coverage) * score).astype(np.float32)

    def calibration(self, rig: Rig) -> torch.Tensor | None:
        """The triangulation maps (1 x S x 6 x H x W) a net whose head reads them needs
        (odmv.models.phase.HEADS); None for others."""
        spec = self.input_spec
        if not reads_maps(spec.get("head")):
            return None
        maps = triangulation_maps(
            rig, self.views, *self.size, spec["period_px"], spec["step"], spec["n_steps"]
        )
        return torch.from_numpy(maps)[None]

    def reference(self, rig: Rig) -> np.ndarray | None:
        """The reference plane's phase (S x 2 x H x W: sin, cos) a net trained with it reads
        beside each image (odmv.data.reference); None for others."""
        spec = self.input_spec
        if not reference_mode(spec.get("reference")):
            return None
        return reference_phase(
            rig, self.views, *self.size, spec["period_px"], spec["step"], spec["n_steps"]
        )

    def rig_inputs(self, rig: Rig) -> dict[str, np.ndarray]:
        """What the net reads from the rig alone, the same for every capture: ``reference``
        and, with the phase head, ``calibration`` (S x 6 x H x W), where it reads them."""
        maps = self.calibration(rig)
        arrays = {"reference": self.reference(rig), "calibration": None}
        if maps is not None:
            arrays["calibration"] = maps[0].numpy()
        return {k: v for k, v in arrays.items() if v is not None}

    def inputs(self, fringes: np.ndarray, rig: Rig, available=None) -> torch.Tensor:
        """The net's input (1 x C x H x W) from linear-intensity images (S x H x W);
        ``available`` (S, 0/1; None: all) marks missing views for a net trained with view
        dropout."""
        x = self.norm.fringes(torch.from_numpy(np.ascontiguousarray(fringes, np.float32)))
        spec = self.input_spec
        ref = self.reference(rig)
        if ref is not None:
            x = network_input(x, torch.from_numpy(ref), reference_mode(spec.get("reference")))
        if spec.get("availability"):  # a net trained with view dropout
            flags = torch.ones(len(self.views)) if available is None else torch.as_tensor(available)
            x = with_availability(x, flags.float())
        return x[None]


def load_predictor(path: str | Path) -> Predictor:
    """A checkpoint (``.ckpt``, run by PyTorch) or an exported ``.onnx`` (run by ONNX Runtime,
    on CUDA where available)."""
    if Path(path).suffix == ".onnx":
        return _onnx_predictor(Path(path))
    return module_predictor(load_module(path).eval(), calibration_of(Path(path)))


def module_predictor(module, error_bars: dict | None = None) -> Predictor:
    """A trained module (eval mode) run by PyTorch as a :class:`Predictor` (with its
    calibration, ``score_mm``: each pixel's uncertainty score)."""

    def run(x: torch.Tensor, calibration: torch.Tensor | None = None) -> dict:
        with torch.no_grad():
            out = module(x, calibration)
            depth = module.depth_mm(out)
            result = {"depth_mm": depth.numpy().astype(np.float32)}
            if "weights" in out:
                result["weights"] = out["weights"].numpy()
            if error_bars is not None:
                result["score_mm"] = pixel_score(out, depth, error_bars["score"]).numpy()
            return result

    head = check_head(module.hparams.net_cfg.get("head"))[0]  # (older checkpoints' spec lacks it)
    return Predictor(
        list(module.hparams.views),
        input_shape(module)[1:],
        module.norm,
        dict(module.hparams.get("input_spec") or {}) | {"head": head},
        run,
        error_bars,
    )


def _onnx_predictor(path: Path) -> Predictor:
    import onnxruntime as ort

    if not path.is_file():
        raise ValueError(f"{path}: no such ONNX model")
    try:
        session = ort.InferenceSession(str(path), providers=ort.get_available_providers())
    except Exception as e:  # ONNX Runtime's own errors (a damaged or foreign file)
        raise ValueError(f"{path}: not a readable ONNX model ({str(e).splitlines()[0]})") from None
    meta = session.get_modelmeta().custom_metadata_map.get(METADATA_KEY)
    if meta is None:
        raise ValueError(f"{path}: no odmv metadata (export it with python -m odmv.export)")
    meta = json.loads(meta)

    names = [o.name for o in session.get_outputs()]
    takes_maps = any(i.name == "calibration" for i in session.get_inputs())

    def run(x: torch.Tensor, calibration: torch.Tensor | None = None) -> dict:
        feed = {"inputs": x.numpy()}
        if takes_maps:
            feed["calibration"] = calibration.numpy()
        return dict(zip(names, session.run(None, feed), strict=True))

    # what the graph takes decides; older exports' spec lacks the head
    head = meta["input_spec"].get("head") or ("phase" if takes_maps else "depth")
    return Predictor(
        meta["views"],
        tuple(meta["input_size"]),
        Normalization(**meta["norm"]),
        meta["input_spec"] | {"head": head},
        run,
        meta.get("error_bars") if "score_mm" in names else None,
    )
