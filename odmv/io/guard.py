"""Outputs never overwrite inputs: an app refuses an output folder that is, or lies inside, one
of its inputs (a dataset, a capture, a source folder) in one line naming both, before it writes
anything. ``overwrite=true`` lets predict write into a capture folder, never into a dataset,
whose ground truth its depth.exr would replace."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path


class OverwriteError(ValueError):
    """An output would overwrite an input."""


def within(path: str | Path, folder: str | Path) -> bool:
    """Whether ``path`` is ``folder`` or lies inside it (links resolved)."""
    p, f = Path(path).resolve(), Path(folder).resolve()
    return p == f or f in p.parents


def refuse_inside(
    key: str,
    outputs: Iterable[str | Path],
    inputs: Iterable[str | Path],
    *,
    protected: Iterable[str | Path] = (),
    overwrite: bool = False,
) -> None:
    """Raise :class:`OverwriteError` for the first of ``outputs`` (the folders setting ``key``
    makes the app write) inside one of ``inputs`` unless ``overwrite``, or inside one of
    ``protected`` (datasets: ground truth) at all."""
    inputs, protected = list(inputs), list(protected)
    for out in outputs:
        for folder in protected:
            if within(out, folder):
                raise OverwriteError(
                    f"{key}: {out} lies inside the dataset {folder}, whose ground truth it "
                    "would overwrite; write elsewhere"
                )
        for folder in [] if overwrite else inputs:
            if within(out, folder):
                raise OverwriteError(
                    f"{key}: {out} is or lies inside the input {folder}; write elsewhere "
                    "(or overwrite=true to write beside its files)"
                )
