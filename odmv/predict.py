"""Depth from fringe images: ``python -m odmv.predict ckpt_path=PATH input=PATH``.

``ckpt_path`` is a training checkpoint (run by PyTorch) or a ``model.onnx`` written by
``python -m odmv.export`` (run by ONNX Runtime); both give the same outputs. ``method=psp``
instead reconstructs classically from full phase-shift sequences
(odmv.classical.reconstruct), no net.

``input`` is one scene or many: a dataset scene folder (``DATASET/scenes/<id>``, calibration
from its manifest), a folder of one image per view (``right.png``, ``up.tif``, ...: EXR, PNG,
TIFF, BMP or NPY; odmv.io.images), a folder of such folders, or a glob. For each scene it
writes ``depth.exr`` (channel Z, camera-axis depth in mm, with unit and provenance in the
header), ``depth.png`` (a preview) and ``points.ply`` (camera frame, mm; valid pixels only,
and with ``drop_unlit`` only pixels some projector lights) into ``out`` (several scenes: one
sub-folder each), and ``page.html``: the depth in 3D beside the inputs (and against the ground
truth where the input is a dataset scene). The intensity scale and any resizing are printed,
never silent.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from odmv.cli import run_app
from odmv.config import app
from odmv.deploy.predict import predict
from odmv.page.document import page_of


@app("predict")
def main(cfg: DictConfig) -> None:
    # a folder the user had is theirs: never removed, even when the prediction fails (odmv.cli)
    results = run_app(lambda: predict(cfg), cfg.out or cfg.paths.output_dir)
    if len(results) == 1:  # (method=psp without a calibration wrote the phase only)
        names = {"depth": "depth (mm)", "uncertainty": "its error bar (mm)"}
        names |= {"points": "point cloud", "phase": "phase (rad)"}
        print("\n".join(f"{names[k]}: {results[0][k]}" for k in names if results[0].get(k)))
    if any("depth" in r for r in results):  # a page needs a depth map
        page = run_app(lambda: page_of(Path(cfg.out or cfg.paths.output_dir)))
        print(f"page: {page} (open it in a browser, offline)")


if __name__ == "__main__":
    main()
