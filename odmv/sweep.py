"""Multirun bookkeeping: each finished job appends its overrides and test metrics as one row of
``<sweep dir>/results.csv`` (a Hydra callback), so a sweep leaves a table, not a folder hunt."""

from __future__ import annotations

import csv
import fcntl
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

RESULTS = "results.csv"


def append_row(path: Path, row: dict) -> None:
    """Append ``row`` under a file lock, widening the header when new columns appear."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(f".{path.name}.lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        rows = list(csv.DictReader(path.open())) if path.exists() else []
        rows.append({k: "" if v is None else v for k, v in row.items()})
        fields = list(dict.fromkeys(k for r in rows for k in r))
        tmp = path.with_suffix(".tmp")
        with tmp.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields, restval="")
            w.writeheader()
            w.writerows(rows)
        tmp.replace(path)


class CollectResults(Callback):
    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs) -> None:
        hc = HydraConfig.get()
        if hc.mode is None or hc.mode.name != "MULTIRUN":
            return
        row = {"job": hc.job.num, "overrides": " ".join(hc.overrides.task)}
        for ov in hc.overrides.task:
            key, _, value = ov.partition("=")
            row[key.lstrip("+~")] = value
        if job_return.status == JobStatus.COMPLETED and isinstance(job_return.return_value, dict):
            for key, value in job_return.return_value.items():
                if key not in row:  # the override columns stay as the user typed them
                    row[key] = "+".join(map(str, value)) if isinstance(value, list) else value
            row["status"] = "ok"
        else:
            row["status"] = "failed"
        append_row(Path(hc.sweep.dir) / RESULTS, row)
