"""Decoded-array cache: one set of memory-mapped .npy files per (dataset, split, settings).

Fringes and depth are stored as float32, lit masks as uint8, so cached items are bit-identical
to items decoded from the EXR files. The cache lives outside the dataset (reading never writes
there) in a folder named by a fingerprint of the manifest, the sample settings and every file's
size and mtime: any change to the dataset selects a new folder, i.e. rebuilds.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from odmv.data.dataset import SampleSpec
from odmv.data.subsets import MASKS
from odmv.io.atomic import DISK_FULL, DiskFullError, remove_abandoned

_ARRAYS = {
    "fringes": np.float32,
    "depth_mm": np.float32,
    "lit": np.uint8,
    **dict.fromkeys(MASKS, np.uint8),
    "phase_target": np.float32,
    "projector_coord": np.float32,
}


def _names(spec: SampleSpec) -> list[str]:
    if not spec.labels:
        return ["fringes"]
    wanted = {
        "phase_target": spec.with_phase or spec.calibration,
        "projector_coord": spec.calibration,
    }
    return [k for k in _ARRAYS if wanted.get(k, True)]


_DONE = "complete.json"


def _allocated(path: Path, dtype, shape: tuple[int, ...]) -> np.memmap:
    """A writable memory-mapped .npy whose blocks are reserved on disk first: a sparse file's
    pages find a full disk only when written, which kills the process with SIGBUS (no message,
    no clean-up); reserved, a full disk is a one-line error here."""
    array = np.lib.format.open_memmap(path, "w+", dtype, shape)
    try:
        with path.open("r+b") as fh:
            os.posix_fallocate(fh.fileno(), 0, path.stat().st_size)
    except OSError as e:
        if e.errno in DISK_FULL:
            need = path.stat().st_size / 2**20
            raise DiskFullError(
                f"{path.parent.parent}: no space left for the decoded-array cache ({path.name} "
                f"needs {need:.1f} MiB); free some, or set data.cache_dir elsewhere"
            ) from None
        if e.errno not in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
            raise
    return array


class ArrayCache:
    """Read side: ``get(i)`` returns the arrays of item i (memory-mapped)."""

    def __init__(self, folder: Path):
        self.folder = folder
        self._arrays = None

    def _open(self) -> dict[str, np.ndarray]:
        # opened lazily, so each DataLoader worker maps the files itself after forking
        if self._arrays is None:
            self._arrays = {p.stem: np.load(p, mmap_mode="r") for p in self.folder.glob("*.npy")}
        return self._arrays

    def get(self, i: int) -> dict[str, np.ndarray]:
        return {k: a[i] for k, a in self._open().items()}

    def __getstate__(self):  # DataLoader workers re-open the maps
        return {"folder": self.folder, "_arrays": None}

    @staticmethod
    def complete(folder: Path) -> bool:
        return (folder / _DONE).is_file()

    @classmethod
    def build(
        cls,
        folder: Path,
        ids: list[str],
        spec: SampleSpec,
        load: Callable[[str], dict[str, np.ndarray]],
        progress=None,
    ) -> ArrayCache:
        """Decode every item with ``load(scene_id)`` into ``folder`` (atomically: a temporary
        folder renamed when complete); reuse it if it is already complete."""
        if cls.complete(folder):
            return cls(folder)
        remove_abandoned(folder)
        tmp = folder.with_name(f".{folder.name}.{os.getpid()}.tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        s, h, w = len(spec.views), spec.height_px, spec.width_px
        shapes = {
            "fringes": (s, h, w),
            "depth_mm": (1, h, w),
            "lit": (s, h, w),
            **dict.fromkeys(MASKS, (1, h, w)),
            "phase_target": (2 * s, h, w),
            "projector_coord": (s, h, w),
        }
        names = _names(spec)
        try:
            out = {
                k: _allocated(tmp / f"{k}.npy", _ARRAYS[k], (len(ids),) + shapes[k]) for k in names
            }
            for i, sid in enumerate(ids):
                raw = load(sid)
                for k in names:
                    out[k][i] = raw[k]
                if progress:
                    progress()
            for a in out.values():
                a.flush()
            (tmp / _DONE).write_text(json.dumps({"ids": ids, "spec": spec.key()}))
            # another process (a DDP rank) may have built the same cache meanwhile: keep its
            if not cls.complete(folder):
                shutil.rmtree(folder, ignore_errors=True)  # an interrupted build's leftover
                try:
                    os.replace(tmp, folder)
                except OSError:  # renamed into place by another process just now
                    if not cls.complete(folder):
                        raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return cls(folder)
