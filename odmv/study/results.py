"""Finished runs placed in the tables' rows: a run (its folder and metrics, held-out scores
included), a cell (one row's runs and their mean ± std over seeds), and how runs are found below
folders and sorted into the rows of :mod:`odmv.study.tables`."""

from __future__ import annotations

import json
from collections import Counter
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

    @property
    def dataset(self) -> str:
        """The dataset's name (its folder's), ``unknown`` where the record predates it."""
        return Path(self.metrics.get("dataset") or "unknown").name

    @property
    def setup(self) -> dict[str, str] | None:
        """What was trained (odmv.training.provenance.training_setup); None in older records."""
        return self.metrics.get("setup")

    @property
    def trained(self) -> tuple[str, str]:
        """What the run's seeds share: its dataset (by manifest fingerprint where recorded)
        and setup. Runs that differ in it are not repeats of one another."""
        data = self.metrics.get("dataset_sha1") or self.dataset
        return data, json.dumps(self.setup, sort_keys=True)

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
    """One row of a table: its runs and their statistics. Where runs of a row trained different
    things (another dataset or setting), each setup is a cell of its own, ``variant`` says
    what sets it apart, and the claims use the ``primary`` one (see :func:`build_tables`)."""

    row: Row
    runs: list[Run] = field(default_factory=list)
    variant: str = ""
    primary: bool = True

    @property
    def label(self) -> str:
        return f"{self.row.label} [{self.variant}]" if self.variant else self.row.label

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
    take the protocol's width. A row's runs that trained different things (Run.trained) are
    split by setup, as cells in a row's place: first the setup on the dataset most runs used,
    with the most runs, which the claims use."""
    rows_of = declared(protocol)
    widths = {row.width for rows in rows_of.values() for row in rows} - {None}
    datasets = Counter(r.trained[0] for r in runs)

    def belongs(run: Run, row: Row) -> bool:
        return run.matches(row) and (row.width is not None or run.width not in widths)

    return {
        name: [
            cell for row in rows for cell in _by_setup(row, [r for r in runs if belongs(r, row)],
                                                       datasets)
        ]
        for name, rows in rows_of.items()
    }  # fmt: skip


def _by_setup(row: Row, runs: list[Run], datasets: Counter) -> list[Cell]:
    groups: dict[tuple[str, str], list[Run]] = {}
    for r in runs:
        groups.setdefault(r.trained, []).append(r)
    if len(groups) <= 1:
        return [Cell(row, runs)]
    order = sorted(groups, key=lambda k: (-datasets[k[0]], -len(groups[k]), k))
    differ = _differences([groups[k][0] for k in order])
    return [
        Cell(row, groups[k], variant, primary=not i)
        for i, (k, variant) in enumerate(zip(order, differ, strict=True))
    ]


def _differences(runs: list[Run], most: int = 4) -> list[str]:
    """What sets each of ``runs`` (one per setup) apart from the others: its dataset where they
    differ, then the settings they do not share (at most ``most``)."""
    names = {r.dataset for r in runs}
    prints = {r.metrics.get("dataset_sha1") for r in runs}
    setups = [r.setup or {} for r in runs]
    keys = sorted({k for s in setups for k in s if len({t.get(k) for t in setups}) > 1})
    out = []
    for r, setup in zip(runs, setups, strict=True):
        said = [f"dataset {r.dataset}"] if len(names) > 1 else []
        if len(names) == 1 and len(prints) > 1:
            said.append(f"dataset sha1 {r.metrics.get('dataset_sha1') or '?'}")
        if r.setup is None and any(setups):
            said.append("setup not recorded")
        elif keys:
            shown = [f"{k}={setup.get(k, '–')}" for k in keys[:most]]
            more = f" (+{len(keys) - most} more)" if len(keys) > most else ""
            said.append(", ".join(shown) + more)
        out.append("; ".join(said))
    return out


def fmt(mean: float, std: float, digits: int = 4) -> str:
    if not np.isfinite(mean):
        return "missing"
    return f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if np.isfinite(std) else "")


def primary(tables: dict[str, list[Cell]]) -> dict[str, list[Cell]]:
    """The tables with one cell a row: what the claims compare (build_tables)."""
    return {name: [c for c in cells if c.primary] for name, cells in tables.items()}
