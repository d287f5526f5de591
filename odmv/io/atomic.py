"""Files written whole or not at all: every file the project writes goes through here.

The temporary file lies beside the target, in the same folder and so on the same file system,
and replaces it by a rename only once it is complete: a reader never sees half a file, and a
failure (a full disk, a killed process) leaves the old target as it was. A temporary file in
/tmp would be copied, not renamed, onto another file system, which truncates the target when
that disk is full.
"""

from __future__ import annotations

import csv
import errno
import glob
import json
import os
import shutil
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

#: errors that mean the target's file system has no room for it
DISK_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}


class DiskFullError(ValueError):
    """No room to write a file; the message is one line naming the file, the folder and what
    it needed (a ValueError: every app reports it in one line, odmv.cli)."""


#: free bytes below which a writer's own error is taken for a full disk
_NO_ROOM_BYTES = 1 << 20


def _no_room(folder: Path) -> bool:
    try:
        return shutil.disk_usage(folder).free < _NO_ROOM_BYTES
    except OSError:
        return False


def temporary(path: Path) -> Path:
    """The name a file is written under before it replaces ``path``."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def remove_abandoned(path: Path) -> None:
    """Remove the temporary files or folders of writes of ``path`` whose process is gone (a
    killed run's); a live process's are its own."""
    for tmp in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        pid = tmp.name[len(path.name) + 2 : -4]
        if pid.isdigit() and not alive(int(pid)):
            if tmp.is_dir():
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink(missing_ok=True)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def write_atomic(path: str | os.PathLike, write: Callable[[Path], object]) -> Path:
    """Create or replace ``path`` with what ``write(tmp)`` writes into the temporary path
    beside it; returns ``path``. On a full disk raises :class:`DiskFullError`; on any error the
    temporary file is gone and an existing ``path`` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_abandoned(path)
    tmp = temporary(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    except Exception as e:
        # torch.save and OpenEXR report a full disk as RuntimeErrors of their own wording
        full = e.errno in DISK_FULL if isinstance(e, OSError) else _no_room(path.parent)
        if full:
            size = tmp.stat().st_size if tmp.exists() else 0
            free = shutil.disk_usage(path.parent).free
            raise DiskFullError(
                f"{path}: no space left on {path.parent} (wrote {size / 2**20:.1f} MiB before it "
                f"ran out, {free / 2**20:.1f} MiB free); nothing was replaced",
            ) from None
        raise
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_text(path: str | os.PathLike, text: str) -> Path:
    return write_atomic(path, lambda tmp: tmp.write_text(text))


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    return write_atomic(path, lambda tmp: tmp.write_bytes(data))


def write_json(path: str | os.PathLike, data: dict) -> Path:
    return write_text(path, json.dumps(data, indent=1) + "\n")


def write_npy(path: str | os.PathLike, array: np.ndarray) -> Path:
    """One array as ``.npy`` (through a file object: numpy appends no suffix)."""

    def write(tmp: Path) -> None:
        with tmp.open("wb") as fh:
            np.save(fh, array)

    return write_atomic(path, write)


def write_npz(path: str | os.PathLike, arrays: dict) -> Path:
    """Named arrays as a compressed ``.npz`` (through a file object: numpy appends no suffix)."""

    def write(tmp: Path) -> None:
        with tmp.open("wb") as fh:
            np.savez_compressed(fh, **arrays)

    return write_atomic(path, write)


def write_csv(path: str | os.PathLike, rows: list[dict]) -> Path:
    """``rows`` as CSV, the header every key of any row in first-seen order (blank where a row
    lacks one)."""
    fields = list(dict.fromkeys(k for r in rows for k in r))

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields, restval="")
            w.writeheader()
            w.writerows(rows)

    return write_atomic(path, write)


@contextmanager
def staged(folder: str | os.PathLike, owned: tuple[str, ...]) -> Iterator[Path]:
    """Files that belong together (a graph and the rig file it reads), written into a hidden
    folder beside ``folder`` and moved into it only when all are written, with Ctrl-C and
    SIGTERM held back meanwhile: an interruption or a failure leaves ``folder`` as it was, and
    a finished set never sits beside the rest of an older one (files named in ``owned`` that
    the new set lacks are removed)."""
    folder = Path(folder)
    folder.absolute().parent.mkdir(parents=True, exist_ok=True)
    remove_abandoned(folder)
    stage = temporary(folder)
    stage.mkdir()
    try:
        yield stage
        held = {signal.SIGINT, signal.SIGTERM}
        signal.pthread_sigmask(signal.SIG_BLOCK, held)
        try:
            folder.mkdir(exist_ok=True)
            for name in owned:
                if not (stage / name).exists():
                    (folder / name).unlink(missing_ok=True)
            for path in stage.iterdir():
                os.replace(path, folder / path.name)
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, held)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
