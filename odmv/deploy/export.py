"""A trained net exported as one set of files: the ONNX graph checked against PyTorch
(odmv.deploy.onnx), the rig's constant inputs (odmv.deploy.rigfile) and its int8 copy checked
on validation scenes (odmv.deploy.quantize); what ``python -m odmv.export`` runs."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from odmv.deploy.onnx import export_onnx
from odmv.deploy.quantize import check_precisions, export_precisions
from odmv.deploy.rigfile import RIG_FILE, export_rig
from odmv.io.atomic import staged

#: the files an export writes: a new set replaces all of an old one
EXPORTED = ("model.onnx", "model.int8.onnx", RIG_FILE)


def export(cfg: DictConfig) -> None:
    """Write the set into a hidden folder beside ``out`` and move it in whole at the end: an
    export stopped or failed midway leaves ``out`` as it was (odmv.io.atomic.staged)."""
    check_precisions(cfg.precisions)
    out = Path(cfg.out)
    lines = []
    with staged(out, EXPORTED) as stage:
        print("exporting the graph and checking it with ONNX Runtime ...", flush=True)
        path, diff = export_onnx(cfg.ckpt_path, stage)
        lines.append(f"{out / path.name}: ONNX Runtime matches PyTorch within {diff:.2e} mm")
        rig, which = export_rig(cfg.ckpt_path, stage, cfg.calibration)
        lines.append(f"{out / rig.name}: what the net reads from the rig, for {which}")
        if "int8" in cfg.precisions:
            print("quantizing to int8 and checking it on the validation scenes ...", flush=True)
        copies = export_precisions(
            cfg.ckpt_path, path, list(cfg.precisions), cfg.check_scenes, cfg.int8_keep_float
        )
        for precision, (copy, mean_mm, max_mm) in copies.items():
            lines.append(
                f"{out / copy.name}: {precision} against float32 on {cfg.check_scenes} validation"
                f" scenes at most: mean |difference| {mean_mm:.4f} mm, largest {max_mm:.3f} mm"
            )
    print("\n".join(lines))
