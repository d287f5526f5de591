"""How every app reports the project's own errors: one line, ``error: <file or key>: <problem>``,
exit status 2, and no empty run folder left behind. ``HYDRA_FULL_ERROR=1`` shows the traceback.

The project's errors (DataError, ManifestError, ExrError, SimulationError, ...) are
ValueErrors that name the file or config key at fault; one raised by a config resolver or a
constructor arrives wrapped by OmegaConf or Hydra and is reported by its own message.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from hydra.errors import InstantiationException
from lightning.pytorch.utilities import rank_zero_only
from omegaconf.errors import OmegaConfBaseException

T = TypeVar("T")

#: What Hydra and the loggers write into a run folder before the first checkpoint; a folder
#: holding only these belongs to a run that failed before it produced anything.
_STARTUP_FILES = {".hydra", "train.log", "evaluate.log", "predict.log", "csv", "tensorboard"}


_WRAPPERS = (OmegaConfBaseException, InstantiationException)


def _one_line(exc: BaseException) -> str:
    key = None
    while isinstance(exc, _WRAPPERS) and exc.__cause__ is not None:
        key = key or getattr(exc, "full_key", None)
        exc = exc.__cause__  # the resolver's or constructor's own message, not the wrapper
    text = str(exc).strip().splitlines()
    line = text[0] if text else type(exc).__name__
    # OmegaConf words a resolver's error as "<Type> raised while resolving interpolation: ..."
    line = re.sub(r"^\w+ raised while resolving interpolation: ", "", line)
    key = key or getattr(exc, "full_key", None)
    return f"{key}: {line}" if key and not line.startswith(f"{key}:") else line


def quiet_lightning() -> None:
    """Lightning's info chatter (tips to install its cloud products, "GPU available: False",
    "was configured so 1 batch per epoch will be used") drowns what the apps print; its
    warnings still show."""
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logging.getLogger(name).setLevel(logging.WARNING)
    # Lightning's own pytree helper builds torch's deprecated LeafSpec; nothing a user can act on
    warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)")
    # the training loss is logged per epoch too, so an epoch shorter than the step interval
    # still draws its curve (train/loss_epoch, odmv.module.FPPModule.training_step)
    warnings.filterwarnings("ignore", message=r"The number of training batches .* logging interval")
    # bf16-mixed keeps the weights in float32, so the summary's 32-bit size is the right one
    warnings.filterwarnings("ignore", message=r"Precision bf16-mixed is not supported by the model")


def tool(name: str) -> str:
    """A command that runs this environment's console script ``name`` as printed, venv
    activated or not: its path beside the interpreter (relative under the current folder)."""
    path = Path(sys.executable).parent / name
    if not path.is_file():
        return name
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def remove_if_empty(folder: Path | None) -> None:
    """Delete a run folder that holds nothing but what every run writes at its start."""
    if folder is None or not folder.is_dir():
        return
    if all(p.name in _STARTUP_FILES for p in folder.iterdir()):
        shutil.rmtree(folder, ignore_errors=True)
        here = Path.cwd().resolve()
        for parent in folder.resolve().parents:  # outputs/<task>/ left empty by it
            if parent == here or here not in parent.parents or any(parent.iterdir()):
                break
            parent.rmdir()


@dataclass(frozen=True)
class JobFailed:
    """What a multirun job's app returns instead of exiting: the sweep goes on with its other
    jobs, odmv.sweep writes ``error`` into the job's results.csv row and exits with 2 at the end."""

    error: str


def run_app(fn: Callable[[], T], run_dir: str | os.PathLike | None = None) -> T | JobFailed:
    """Run an app's body; on one of the project's errors print one line and exit with 2
    (in a multirun: return JobFailed)."""
    quiet_lightning()
    try:
        return fn()
    except (ValueError, *_WRAPPERS) as exc:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        line = _one_line(exc)
        if rank_zero_only.rank == 0:  # DDP ranks fail alike; one line is enough
            print(f"error: {line}", file=sys.stderr)
        remove_if_empty(Path(run_dir) if run_dir else None)
        if in_multirun():
            return JobFailed(line)
        sys.exit(2)


def in_multirun() -> bool:
    """Whether this process runs a job of a Hydra multirun (-m)."""
    from hydra.core.hydra_config import HydraConfig

    return HydraConfig.initialized() and str(HydraConfig.get().mode) == "RunMode.MULTIRUN"


def task_overrides() -> list[str]:
    """The command line's overrides of the running Hydra app (empty outside one)."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []


def set_threads(threads: int | None) -> None:
    """Fix torch's intra-op thread count (None: torch's default). Floating-point sums split by
    thread count, so one seed trained on two counts gives two runs; a protocol pins it."""
    if threads is not None:
        if int(threads) < 1:
            raise ValueError(f"threads: {threads}; a positive thread count, or null")
        import torch

        torch.set_num_threads(int(threads))


def rank_zero_print(text: str) -> None:
    """Print once, from the first process of a multi-process (DDP) run."""
    if rank_zero_only.rank == 0:
        print(text, flush=True)
