"""Multirun bookkeeping: each finished job appends its overrides and test metrics as one row of
``<sweep dir>/results.csv`` (a Hydra callback), so a sweep leaves a table, not a folder hunt."""

from __future__ import annotations

import csv
import fcntl
import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from odmv.cli import JobFailed, tool
from odmv.io.atomic import write_csv, write_text

RESULTS = "results.csv"
SUMMARY = "summary.md"


def append_row(path: Path, row: dict) -> None:
    """Append ``row`` under a file lock, widening the header when new columns appear."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(f".{path.name}.lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        rows = list(csv.DictReader(path.open())) if path.exists() else []
        rows.append({k: "" if v is None else v for k, v in row.items()})
        write_csv(path, rows)


class CollectResults(Callback):
    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        # a search's SQLite study (hparams_search) lives beside the sweeps, in multirun/
        storage = str(config.hydra.sweeper.get("storage") or "")
        if storage.startswith("sqlite:///"):
            Path(storage.removeprefix("sqlite:///")).parent.mkdir(parents=True, exist_ok=True)

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs) -> None:
        hc = HydraConfig.get()
        if hc.mode is None or hc.mode.name != "MULTIRUN":
            return
        row = {"job": hc.job.num, "overrides": " ".join(hc.overrides.task)}
        for ov in hc.overrides.task:
            key, _, value = ov.partition("=")
            row[key.lstrip("+~")] = value
        value = job_return._return_value  # the property raises for a failed job
        if job_return.status == JobStatus.COMPLETED and isinstance(value, dict):
            for key, v in value.items():
                # the override columns stay as the user typed them; the setup is in metrics.json
                if key not in row and not isinstance(v, dict):
                    row[key] = "+".join(map(str, v)) if isinstance(v, list) else v
            row["status"] = "ok"
        else:
            row["status"] = "failed"
            row["error"] = value.error if isinstance(value, JobFailed) else _one_line(value)
        append_row(Path(hc.sweep.dir) / RESULTS, row)

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        path = Path(config.hydra.sweep.dir) / RESULTS
        rows = list(csv.DictReader(path.open())) if path.is_file() else []
        metric = config.get("optimized_metric")
        ranked = bool(metric and any(r.get(metric) for r in rows))
        if ranked:
            direction = str(config.hydra.sweeper.get("direction", "minimize"))
            write_summary(path.with_name(SUMMARY), rows, metric, direction == "maximize")
        if rows:
            print(
                f"sweep: {len(rows)} jobs in {path.parent}; every job's overrides and metrics: "
                f"{path}" + (f"; ranked by {metric}: {path.with_name(SUMMARY)}" if ranked else "")
                + f"\n  tables and figures: {tool('python')} -m odmv.report "
                f"runs=[{path.parent}] out={path.parent / 'report'}",
                flush=True,
            )  # fmt: skip
        failed = [r for r in rows if r.get("status") == "failed"]
        if failed:
            print(
                f"error: {path}: {len(failed)} of {len(rows)} jobs failed (their rows say why)",
                file=sys.stderr,
            )
            sys.exit(2)


def write_summary(path: Path, rows: list[dict], metric: str, maximize: bool) -> None:
    """``summary.md``: the jobs ranked by ``metric``, the best named first (and printed)."""
    done = [r for r in rows if r.get("status") == "ok" and r.get(metric)]
    done.sort(key=lambda r: float(r[metric]), reverse=maximize)
    best = done[0]
    line = f"best: job {best['job']} ({path.parent / best['job']}), {metric} = {best[metric]}"
    table = [f"| job | {metric} | overrides |", "|---:|---:|---|"]
    table += [f"| {r['job']} | {float(r[metric]):.6g} | {r['overrides']} |" for r in done]
    failed = len(rows) - len(done)
    text = f"# Sweep summary\n\n{line}\n\n" + "\n".join(table) + "\n"
    if failed:
        text += f"\n{failed} job(s) failed or gave no {metric} (results.csv says why).\n"
    write_text(path, text)
    print(line, flush=True)


def _one_line(value) -> str:
    text = str(value).strip().splitlines()
    return f"{type(value).__name__}: {text[0]}" if text else type(value).__name__
