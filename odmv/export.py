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

from odmv.cli import app, run_app
from odmv.deploy.onnx import export_onnx
from odmv.deploy.quantize import check_precisions, export_precisions
from odmv.deploy.rigfile import export_rig


def export(cfg: DictConfig) -> None:
    check_precisions(cfg.precisions)
    path, diff = export_onnx(cfg.ckpt_path, cfg.out)
    print(f"{path}: ONNX Runtime matches PyTorch within {diff:.2e} mm")
    rig, which = export_rig(cfg.ckpt_path, cfg.out, cfg.calibration)
    print(f"{rig}: what the net reads from the rig, for {which}")
    copies = export_precisions(
        cfg.ckpt_path, path, list(cfg.precisions), cfg.check_scenes, cfg.int8_keep_float
    )
    for precision, (copy, mean_mm, max_mm) in copies.items():
        print(
            f"{copy}: {precision} against float32 on {cfg.check_scenes} validation scenes "
            f"at most: mean |difference| {mean_mm:.4f} mm, largest {max_mm:.3f} mm"
        )


@app("export")
def main(cfg: DictConfig) -> None:
    run_app(lambda: export(cfg))


if __name__ == "__main__":
    main()
