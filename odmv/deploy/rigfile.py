"""``rig.npz`` beside an exported graph: what the net reads from the rig alone, the same for
every capture (the reference plane's phase, and with the phase head the triangulation maps),
so a consumer of the graph needs ONNX Runtime and numpy only (docs/deploy.md)."""

from __future__ import annotations

from pathlib import Path

from odmv.deploy.inference import module_predictor
from odmv.io.atomic import write_npz
from odmv.io.calibration import load_calibration
from odmv.io.manifest import MANIFEST, load_manifest
from odmv.rig import Rig
from odmv.training.module import load_module

RIG_FILE = "rig.npz"


def export_rig(ckpt_path: str | Path, out_dir: str | Path, calibration=None) -> tuple[Path, str]:
    """Write ``out_dir/rig.npz`` for the rig of ``calibration`` (an OpenCV-style file), else of
    the run's dataset, else the paper's; returns its path and which rig it holds."""
    module = load_module(ckpt_path).eval()
    if calibration:
        rig, which = load_calibration(calibration), f"calibration {calibration}"
    else:
        root = (module.hparams.data_cfg or {}).get("root")
        if root and (Path(root) / MANIFEST).is_file():
            rig, which = load_manifest(root).rig, f"the run's dataset {root}"
        else:
            missing = f"; the run's dataset {root} is not here" if root else ""
            rig, which = Rig(), f"the paper's default rig{missing} (give calibration=FILE)"
    arrays = module_predictor(module).rig_inputs(rig)
    return write_npz(Path(out_dir) / RIG_FILE, arrays), which
