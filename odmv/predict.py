"""Depth from your own fringe images: ``python -m odmv.predict ckpt_path=PATH input=PATH``.

``ckpt_path`` is a training checkpoint (run by PyTorch) or a ``model.onnx`` written by
``python -m odmv.export`` (run by ONNX Runtime); both give the same outputs.

``input`` is either a scene folder of a dataset (``DATASET/scenes/<id>``, calibration from its
manifest) or a folder holding one image per view named ``<view>.exr`` (e.g. ``right.exr``,
``up.exr``; channel ``Y`` or the only channel), linear intensity like the training data, with
the rig from ``manifest=PATH`` or the default rig. Writes ``depth.exr`` (channel Z, camera-axis
z in mm) and ``points.ply`` (one point per pixel, camera frame, mm) into ``out`` (default: the
run folder).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

import odmv.config  # noqa: F401  (registers the config resolvers)
from odmv.cli import run_app
from odmv.data.dataset import DataError, SampleSpec, load_scene
from odmv.data.normalize import Normalization
from odmv.data.reference import network_input, reference_mode, reference_phase
from odmv.export import METADATA_KEY
from odmv.io.exr import ExrError, read_exr, write_exr
from odmv.io.manifest import MANIFEST, load_manifest
from odmv.module import load_module
from odmv.rig import Camera, Rig
from odmv.simulate import CONF_DIR


def _resize_area(a: np.ndarray, h: int, w: int) -> np.ndarray:
    t = torch.from_numpy(np.ascontiguousarray(a, np.float32))[None]
    return torch.nn.functional.interpolate(t, size=(h, w), mode="area")[0].numpy()


def read_inputs(path: Path, views: list[str], size: tuple[int, int], manifest: str | None):
    """(fringes S x H x W linear intensity at ``size``, rig) from a scene or an image folder."""
    dataset = path.parent.parent
    if (dataset / MANIFEST).is_file() and path.parent.name == "scenes":
        m = load_manifest(dataset)
        spec = SampleSpec(
            tuple(views),
            *size,
            m.fringe.resolve_frequency(m.fringe.train_frequency),
            m.fringe.train_step,
        )
        return load_scene(m, path.name, spec)["fringes"], m.rig
    if not path.is_dir():
        raise DataError(f"{path}: input must be a scene folder or a folder of <view>.exr images")
    images = []
    for v in views:
        f = path / f"{v}.exr"
        try:
            chans = read_exr(f)
        except ExrError as e:
            raise DataError(f"{e} (the checkpoint needs views {views})") from None
        img = chans["Y"] if "Y" in chans else next(iter(chans.values()))
        if len(chans) > 1 and "Y" not in chans:
            raise DataError(f"{f}: several channels and none named 'Y'")
        images.append(img.astype(np.float32))
    shapes = {a.shape for a in images}
    if len(shapes) != 1:
        raise DataError(f"{path}: the view images differ in size {sorted(shapes)}")
    rig = load_manifest(manifest).rig if manifest else Rig()
    return _resize_area(np.stack(images), *size), rig


def point_cloud(depth_mm: np.ndarray, cam: Camera) -> np.ndarray:
    """Camera-frame points (N x 3, mm) of every pixel centre at its depth."""
    _, d = cam.centre_rays()
    d_cam = d.reshape(-1, 3) @ cam.R.T  # camera-frame directions
    pts = d_cam / d_cam[:, 2:3] * depth_mm.reshape(-1, 1)
    return pts[np.isfinite(pts).all(1)]


def write_ply(path: Path, points: np.ndarray) -> Path:
    """Binary little-endian PLY of float32 xyz points, written atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment odmv depth, camera frame, mm\n"
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n"
    )
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(points.astype("<f4").tobytes())
    tmp.replace(path)
    return path


@dataclass
class Predictor:
    """A trained net with what it needs to turn images into depth: its views in order, input
    size (H, W), normalization and input settings, and ``run``: net input -> depth (mm)."""

    views: list[str]
    size: tuple[int, int]
    norm: Normalization
    input_spec: dict
    run: Callable[[torch.Tensor], np.ndarray]

    def inputs(self, fringes: np.ndarray, rig: Rig) -> torch.Tensor:
        """The net's input (1 x C x H x W) from linear-intensity images (S x H x W)."""
        x = self.norm.fringes(torch.from_numpy(np.ascontiguousarray(fringes, np.float32)))
        spec = self.input_spec
        mode = reference_mode(spec.get("reference"))
        if mode:  # the reference-plane phase from the rig's calibration
            ref = reference_phase(
                rig, self.views, *self.size, spec["period_px"], spec["step"], spec["n_steps"]
            )
            x = network_input(x, torch.from_numpy(ref), mode)
        return x[None]


def load_predictor(path: str | Path) -> Predictor:
    """A checkpoint (``.ckpt``, run by PyTorch) or an exported ``.onnx`` (run by ONNX Runtime,
    on CUDA where available)."""
    if Path(path).suffix == ".onnx":
        return _onnx_predictor(Path(path))
    module = load_module(path).eval()
    res = (module.hparams.data_cfg or {}).get("resolution", 480)

    def run(x: torch.Tensor) -> np.ndarray:
        with torch.no_grad():
            return module.depth_mm(module(x)).numpy().astype(np.float32)

    return Predictor(
        list(module.hparams.views),
        (res, res) if isinstance(res, int) else tuple(res),
        module.norm,
        dict(module.hparams.get("input_spec") or {}),
        run,
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

    def run(x: torch.Tensor) -> np.ndarray:
        return session.run(None, {"inputs": x.numpy()})[0]

    return Predictor(
        meta["views"],
        tuple(meta["input_size"]),
        Normalization(**meta["norm"]),
        meta["input_spec"],
        run,
    )


def predict(cfg: DictConfig) -> dict[str, Path]:
    predictor = load_predictor(cfg.ckpt_path)
    fringes, rig = read_inputs(Path(cfg.input), predictor.views, predictor.size, cfg.manifest)
    depth_mm = predictor.run(predictor.inputs(fringes, rig))[0, 0].astype(np.float32)
    out = Path(cfg.out or cfg.paths.output_dir)
    depth_path = write_exr(out / "depth.exr", {"Z": depth_mm})
    h, w = predictor.size
    ply_path = write_ply(out / "points.ply", point_cloud(depth_mm, rig.camera_at(w, h)))
    return {"depth": depth_path, "points": ply_path}


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="predict")
def main(cfg: DictConfig) -> None:
    # a folder the user named is theirs: never removed, even when the prediction fails
    paths = run_app(lambda: predict(cfg), None if cfg.out else cfg.paths.output_dir)
    print(f"depth (mm): {paths['depth']}\npoint cloud: {paths['points']}")


if __name__ == "__main__":
    main()
