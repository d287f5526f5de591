"""OpenEXR 3.x reading and writing of named float channels, with one-line errors.

Writes are atomic: the image goes to a temporary name in the target folder and is renamed into
place, so a crash never leaves a half-written file under the final name.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import OpenEXR

from odmv.io.atomic import write_atomic

_MAGIC = b"\x76\x2f\x31\x01"

COMPRESSIONS = {
    "none": OpenEXR.NO_COMPRESSION,
    "zip": OpenEXR.ZIP_COMPRESSION,
    "zips": OpenEXR.ZIPS_COMPRESSION,
    "zstd": OpenEXR.ZSTD_COMPRESSION,
    "piz": OpenEXR.PIZ_COMPRESSION,
    "rle": OpenEXR.RLE_COMPRESSION,
}
_DTYPES = (np.dtype(np.float32), np.dtype(np.float16))


class ExrError(ValueError):
    """A one-line, file-naming error about an EXR file."""

    def __init__(self, path: str | os.PathLike, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = str(path)
        self.problem = problem


def write_exr(
    path: str | os.PathLike,
    channels: Mapping[str, np.ndarray],
    compression: str = "zip",
    attributes: Mapping[str, str] | None = None,
) -> Path:
    """Write 2D float32/float16 arrays as named channels of one scanline EXR, atomically.

    ``compression`` is one of ``none``, ``zip``, ``zips``, ``zstd``, ``piz``, ``rle``; all are
    lossless, so values round-trip bit-exactly. ``attributes`` adds string header entries.
    """
    path = Path(path)
    if not channels:
        raise ExrError(path, "nothing to write: no channels given")
    if compression not in COMPRESSIONS:
        raise ExrError(
            path, f"unknown compression {compression!r}; use one of {list(COMPRESSIONS)}"
        )
    shape = None
    data = {}
    for name, arr in channels.items():
        arr = np.asarray(arr)
        if arr.dtype not in _DTYPES:
            raise ExrError(path, f"channel {name!r} has dtype {arr.dtype}; use float32 or float16")
        if arr.ndim != 2 or (shape is not None and arr.shape != shape):
            raise ExrError(path, f"channel {name!r} has shape {arr.shape}; need equal 2D shapes")
        shape = arr.shape
        # OpenEXR.File adopts the arrays it is given; pass copies so callers keep theirs.
        data[name] = np.ascontiguousarray(arr).copy()
    header = {"compression": COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
    header.update(dict(attributes or {}))

    def write(tmp: Path) -> None:
        with OpenEXR.File(header, data) as f:
            f.write(str(tmp))

    return write_atomic(path, write)


def _open(path: Path, header_only: bool) -> OpenEXR.File:
    if not path.is_file():
        raise ExrError(path, "no such file")
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic != _MAGIC:
        raise ExrError(path, "not an OpenEXR file (bad magic number)")
    try:
        return OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
    except Exception as exc:  # the C++ library raises plain RuntimeErrors with long texts
        detail = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise ExrError(path, f"unreadable or truncated EXR ({detail})") from None


def exr_channels(path: str | os.PathLike) -> dict[str, tuple[int, int]]:
    """Channel names and (height, width) of an EXR, reading the header only."""
    path = Path(path)
    header = _open(path, header_only=True).header()
    (x0, y0), (x1, y1) = header["dataWindow"]
    shape = (int(y1 - y0 + 1), int(x1 - x0 + 1))
    return {ch.name: shape for ch in header["channels"]}


def read_exr(
    path: str | os.PathLike, channels: Iterable[str] | None = None
) -> dict[str, np.ndarray]:
    """Read named channels (all when None) as 2D arrays in their stored dtype."""
    path = Path(path)
    f = _open(path, header_only=False)
    try:
        stored = {name: ch.pixels for name, ch in f.channels().items()}
    except Exception:  # the library reports a short read as a part-index error
        stored = {}
    if not stored or any(p is None for p in stored.values()):
        raise ExrError(path, "truncated or corrupt pixel data") from None
    if channels is None:
        return stored
    out = {}
    for name in channels:
        if name not in stored:
            raise ExrError(path, f"missing channel {name!r} (has {sorted(stored)})")
        out[name] = stored[name]
    return out


def read_channel(path: str | os.PathLike, name: str) -> np.ndarray:
    """Read one channel as a 2D array."""
    return read_exr(path, [name])[name]
