"""Export a trained net to ONNX: ``python -m odmv.export ckpt_path=CKPT out=DIR``.

Writes ``DIR/model.onnx`` and checks ONNX Runtime against PyTorch on it; what the graph takes
and gives: :mod:`odmv.deploy.onnx`.
"""

from __future__ import annotations

from omegaconf import DictConfig

from odmv.cli import app, run_app
from odmv.deploy.onnx import export_onnx


@app("export")
def main(cfg: DictConfig) -> None:
    path, diff = run_app(lambda: export_onnx(cfg.ckpt_path, cfg.out))
    print(f"{path}: ONNX Runtime matches PyTorch within {diff:.2e} mm")


if __name__ == "__main__":
    main()
