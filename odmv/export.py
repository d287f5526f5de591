"""Export a trained net to ONNX: ``python -m odmv.export ckpt_path=CKPT out=DIR``
(``precisions=[float32,int8]`` adds an int8 copy).

Writes ``DIR/model.onnx`` and checks ONNX Runtime against PyTorch on it (what the graph takes
and gives: :mod:`odmv.deploy.onnx`); ``DIR/rig.npz``, what the net reads from the rig
(``calibration=FILE``; default: the run's dataset's rig; :mod:`odmv.deploy.rigfile`); the int8
copy ``DIR/model.int8.onnx``, checked against the float32 graph on the run's validation scenes
(:mod:`odmv.deploy.quantize`).
"""

from __future__ import annotations

from omegaconf import DictConfig

from odmv.cli import run_app
from odmv.config import app
from odmv.deploy.export import export


@app("export")
def main(cfg: DictConfig) -> None:
    run_app(lambda: export(cfg), cfg.out)


if __name__ == "__main__":
    main()
