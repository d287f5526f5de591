"""The run folder as the study tools read it: how finished runs are found and read (what a
run folder holds: :mod:`odmv.io.runfolder`; checkpoints: ``checkpoints/best-EPOCH.ckpt`` and
``last.ckpt``)."""

from __future__ import annotations

import glob
from pathlib import Path

import numpy as np

from odmv.config import CONF_DIR  # noqa: F401  (registers the config resolvers)
from odmv.training.checkpoint import best_checkpoint
from odmv.training.evaluation import checkpoint_datamodule
from odmv.training.module import load_module


def run_data(run: Path, stage: str, views: list[str] | None = None):
    """A finished run's best checkpoint (eval mode) and its data module set up for ``stage``,
    with the run's data settings (``views``: other views than the run's)."""
    return checkpoint_data(best_checkpoint(run)[0], stage, views)


def checkpoint_data(path: Path, stage: str | None, views: list[str] | None = None):
    """A checkpoint's module (eval mode) and its data module set up for ``stage`` (None: every
    split), reading the checkpoint's dataset (``views``: other views than its own); a bad
    checkpoint raises CheckpointError naming it."""
    module = load_module(path).eval()
    views = list(module.hparams.views) if views is None else views
    return module, checkpoint_datamodule(module, stage, views=views)


def run_groups(arg: str, marker: str) -> tuple[str, list[Path]]:
    """``LABEL=GLOB`` as the label and the matched run folders that hold ``marker``."""
    if "=" not in arg:
        raise ValueError(f"{arg}: give LABEL=GLOB, e.g. 'S=4=outputs/sweep/*views=4*'")
    label, pattern = arg.rsplit("=", 1)  # labels may hold "=" (S=4), globs do not
    found = sorted(Path(p) for p in glob.glob(pattern) if (Path(p) / marker).is_file())
    if not found:
        raise ValueError(f"{arg}: no run folder matches {pattern} (holding {marker})")
    return label, found


def load_predictions(folder: Path, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scene ids, predicted and true depth maps (mm) of one run's predictions file."""
    with np.load(folder / name) as z:
        return z["scene_id"], z["pred_mm"], z["depth_mm"]
