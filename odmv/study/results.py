"""Finished runs placed in the tables' rows: a run (its folder and metrics, held-out scores
included), a cell (one row's runs and their mean ± std over seeds), and how runs are found below
folders and sorted into the rows of :mod:`odmv.study.tables`."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from odmv.io.runfolder import FAILED, HELDOUT, LOCK
from odmv.io.runfolder import METRICS as METRICS_JSON
from odmv.study.tables import Row
from odmv.study.tables import tables as declared

METRICS = ("mae_mm", "mse_mm2", "rmse_mm")
#: the subsets where the first view (the one of every S = 1 row) has no fringe and another
#: view has, as the report names them (odmv.data.subsets); newer than the others, so older
#: records lack them
FIRST_VIEW = {"first_unlit": "first-unlit", "first_shadowed": "first-shadowed"}
#: the pixels away from depth jumps and the band along them (odmv.training.metrics): a net that
#: measures is judged on the first, edge blur on the second; older records lack them
EDGES = {"interior": "interior", "edge": "edge"}
#: the held-out set's columns (odmv.study.heldout): every pixel, then the subsets as named above
HELDOUT_SUBSETS = {"all": "", "shadowed": "shadowed"} | FIRST_VIEW | {"interior": "interior"}
SPLITS = {"test": "test split", "heldout": "held-out"}  # where a claim is judged


class ReportError(ValueError):
    """A one-line error naming the folder at fault."""


@dataclass
class Run:
    folder: Path
    metrics: dict

    @property
    def model(self) -> str:
        return self.metrics.get("model", "")

    @property
    def n_views(self) -> int:
        return len(self.metrics.get("views") or [])

    @property
    def width(self) -> int | None:
        return self.metrics.get("width")

    def matches(self, row: Row) -> bool:
        if (self.model, self.n_views) != (row.model, row.views):
            return False
        if self.metrics.get("head", "depth") != row.head:  # records before heads were depth
            return False
        if self.metrics.get("capture") != row.capture:  # a classical row on fewer images
            return False
        if row.width is not None and self.width != row.width:
            return False
        return row.ablation is None or self.metrics.get("ablation") == row.ablation


@dataclass
class Cell:
    """One row of a table: its runs and their statistics."""

    row: Row
    runs: list[Run] = field(default_factory=list)

    def values(self, key: str) -> np.ndarray:
        return np.array([float(r.metrics.get(key, np.nan)) for r in self.runs], float)

    def by_seed(self) -> list[Run]:
        """The runs in seed order."""
        return sorted(self.runs, key=lambda r: r.metrics.get("seed", 0))

    def stat(self, key: str) -> tuple[float, float]:
        v = self.values(key)
        v = v[np.isfinite(v)]
        if not len(v):
            return np.nan, np.nan
        return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else np.nan


#: what a training leaves in its folder before its metrics: a log, checkpoints, the lock a
#: killed run leaves, the error of a failed one
STARTED = ("train.log", "checkpoints", LOCK, FAILED)


def find_runs(paths: list[Path]) -> tuple[list[Run], list[Path]]:
    """Finished runs (folders with metrics.json) and unfinished ones (started, failed or
    killed: STARTED, no metrics) below ``paths``."""
    runs, pending = [], []
    for p in paths:
        if not p.is_dir():
            raise ReportError(f"{p}: no such folder")
        for folder in sorted({f.parent for f in p.rglob(METRICS_JSON)}):
            try:
                metrics = json.loads((folder / METRICS_JSON).read_text())
            except (OSError, json.JSONDecodeError) as e:
                raise ReportError(f"{folder / METRICS_JSON}: unreadable ({e})") from None
            if "test/mae_mm" in metrics and "model" not in metrics:
                continue  # odmv.evaluate's of a checkpoint (the demo's evaluation/), not a run
            if "test/mae_mm" not in metrics or "model" not in metrics:
                raise ReportError(f"{folder / METRICS_JSON}: not a test result of odmv.train")
            runs.append(Run(folder, metrics | _heldout(folder)))
        for name in STARTED:
            for mark in p.rglob(name):
                if not (mark.parent / METRICS_JSON).is_file():
                    pending.append(mark.parent)
    return runs, sorted(set(pending))


def _heldout(folder: Path) -> dict:
    """A run's held-out scores (odmv.study.heldout) as ``heldout/...`` metrics; none where it was
    not scored."""
    path = folder / HELDOUT
    if not path.is_file():
        return {}
    try:
        held = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ReportError(f"{path}: unreadable ({e})") from None
    return {f"heldout/{k[5:]}": v for k, v in held.items() if k.startswith("test/")}


def build_tables(runs: list[Run], protocol: str | None = None) -> dict[str, list[Cell]]:
    """Each table's rows (odmv.study.tables, for ``protocol``) with their runs. A run that a
    row of its own width claims (ODMV-Net at width 24) belongs to that row only; the other rows
    take the protocol's width."""
    rows_of = declared(protocol)
    widths = {row.width for rows in rows_of.values() for row in rows} - {None}

    def belongs(run: Run, row: Row) -> bool:
        return run.matches(row) and (row.width is not None or run.width not in widths)

    return {
        name: [Cell(row, [r for r in runs if belongs(r, row)]) for row in rows]
        for name, rows in rows_of.items()
    }


def fmt(mean: float, std: float, digits: int = 4) -> str:
    if not np.isfinite(mean):
        return "missing"
    return f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if np.isfinite(std) else "")
