"""The files of a run folder, named once. A finished run (``python -m odmv.train``, the
classical row, or a reproduction's record of one) holds ``metrics.json`` (its test metrics,
settings and provenance) and, where they were written or kept: ``heldout.json`` (its scores on
the held-out set), ``robustness.json`` (its scores on shifted twins of its dataset),
``test_scenes.csv`` (per-scene errors), ``test_predictions.npz`` (predicted
and true depth in mm), ``.hydra/config.yaml`` and ``checkpoints/``; while a training writes into
it, ``run.lock`` (the training's pid; odmv.training.runlock). How runs are found and read:
:mod:`odmv.study.records`."""

import os
import shutil
from pathlib import Path

from odmv.io.atomic import alive

METRICS = "metrics.json"
HELDOUT = "heldout.json"
SCENES_CSV = "test_scenes.csv"
PREDICTIONS = "test_predictions.npz"
CONFIG = ".hydra/config.yaml"
ROBUSTNESS = "robustness.json"
LOCK = "run.lock"  # the pid of the training writing into the folder
FAILED = "failed.txt"  # a failed training's error, beside what it wrote
CALIBRATION_CHECK = "calibration_check.json"  # a fine-tune's check of its starting net
PRIOR = "prior.json"  # the prior probe (odmv.study.prior): MAE with the scene moved
UNCERTAINTY = "uncertainty.json"  # the error bars' calibration (odmv.study.uncertainty)

#: where a checkout keeps its datasets (conf/paths/default.yaml's data_dir)
DATA_DIR = "data"


def portable(path: str | Path, base: str | Path | None = None) -> str:
    """``path`` as a record stores it: relative to ``base`` (default: the working directory,
    the checkout a run or study starts in) where it lies below it, else absolute."""
    try:
        return str(Path(path).resolve().relative_to(Path(base or Path.cwd()).resolve()))
    except ValueError:
        return str(Path(path).absolute())


def portable_record(metrics: dict, run: Path) -> dict:
    """A run's metrics as its ``metrics.json`` stores them: the best checkpoint relative to the
    run folder (it moves with it), the dataset :func:`portable`."""
    out = dict(metrics)
    if out.get("best_checkpoint"):
        out["best_checkpoint"] = portable(out["best_checkpoint"], run)
    if out.get("dataset"):
        out["dataset"] = portable(out["dataset"])
    return out


#: a run folder's files that are text, and may name the checkout's own paths
_TEXT = {".json", ".yaml", ".csv", ".out", ".txt", ".md"}


def kept_copy(source: Path, target: Path) -> None:
    """Copy a run's file into a record that may be committed: in a text file the checkout's
    own absolute path (the working directory, as named and resolved) is left out, so what the
    record names under it is relative to the checkout (a log's library paths, a config's
    folders); other files are copied as they are."""
    if source.suffix not in _TEXT:
        shutil.copy2(source, target)
        return
    text = source.read_text()
    for base in {str(Path.cwd().resolve()), str(Path.cwd().absolute())}:
        text = text.replace(base.rstrip("/") + "/", "")
    target.write_text(text)
    shutil.copystat(source, target)


def recorded_dataset(metrics: dict, run: Path) -> Path:
    """The dataset the record (or checkpoint) of ``run`` names: where it says; a relative path
    is relative to the folder the run was started in, so below the working directory or below
    one of the run folder's parents (a page made from elsewhere); else, for a record written in
    a folder since moved or on another machine, the folder of that name in the ``data/`` of one
    of the run folder's parents (the checkout it moved with) or of the working directory; the
    recorded path if none is there (its reader says so)."""
    path = Path(metrics["dataset"])
    if path.is_dir():
        return path
    parents = Path(run).resolve().parents
    for base in [] if path.is_absolute() else parents:
        if (base / path).is_dir():
            return base / path
    for base in (*parents, Path(".")):
        if (base / DATA_DIR / path.name).is_dir():
            return base / DATA_DIR / path.name
    return path


def lock_holder(folder: Path) -> int | None:
    """The pid of another live process that holds ``folder`` (its ``run.lock``), else None:
    what is in such a folder is that process's, and nothing else may remove or replace it."""
    lock = Path(folder) / LOCK
    try:
        text = lock.read_text().strip()
    except OSError:
        return None
    holder = int(text) if text.isdigit() else None
    return holder if holder is not None and holder != os.getpid() and alive(holder) else None
