"""A run folder belongs to one run. While a training writes into it, ``run.lock`` holds its pid,
and a second training into the folder is refused naming it; a folder holding a finished run
or another run's checkpoints is refused for a new training (``resume=DIR`` continues it); a
run that fails leaves ``failed.txt`` with its error beside what it wrote."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from lightning.pytorch.utilities import rank_zero_only

from odmv.io.atomic import write_text
from odmv.io.runfolder import FAILED, LOCK, METRICS, lock_holder
from odmv.training.checkpoint import CheckpointError


class RunFolderError(ValueError):
    """The run folder is another run's."""


def check_not_held(folder: Path) -> None:
    """Refuse a folder another live training is writing into (before anything touches it);
    a DDP run's other ranks write into the folder its first process holds."""
    if rank_zero_only.rank != 0:
        return
    holder = lock_holder(folder)
    if holder is not None:
        raise RunFolderError(
            f"{folder}: another run (pid {holder}) is writing into it; wait for it to end, "
            "or train into another folder"
        )


def check_new_run(folder: Path) -> None:
    """Refuse to start a new training in a folder that holds a finished or trained run."""
    if (folder / METRICS).is_file():
        raise RunFolderError(
            f"{folder}: holds a finished run ({METRICS}); train into a new folder, or continue "
            f"it with resume={folder}"
        )
    if any((folder / "checkpoints").glob("*.ckpt")):
        raise RunFolderError(
            f"{folder}: holds another run's checkpoints; continue it with resume={folder}, or "
            "train into a new folder"
        )


@contextmanager
def holding(folder: Path) -> Iterator[None]:
    """Hold ``folder`` for this process while the block runs (only the first process of a DDP
    run: its other ranks write into the folder it holds)."""
    if rank_zero_only.rank != 0:
        yield
        return
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / LOCK
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        check_not_held(folder)
        fd = os.open(lock, os.O_WRONLY | os.O_TRUNC)  # a killed run's lock (or this process's)
    with os.fdopen(fd, "w") as fh:
        fh.write(f"{os.getpid()}\n")
    (folder / FAILED).unlink(missing_ok=True)
    try:
        yield
    except CheckpointError:  # a checkpoint that does not fit: the command's, not the run's fault
        raise
    except BaseException as exc:
        line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        write_text(folder / FAILED, f"{type(exc).__name__}: {line}\n")
        raise
    finally:
        lock.unlink(missing_ok=True)
