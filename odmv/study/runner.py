"""The job runner behind ``python -m odmv.reproduce``: a protocol's tables or a study's own
rows as jobs, each a run folder whose configuration key says whether it is done, stale or
interrupted; trained one by one in a clean process, scored on the held-out set and the
shifted twins where asked, kept as records, and reported (what it does, step by step: that
app's docstring)."""

from __future__ import annotations

import fnmatch
import hashlib
import inspect
import itertools
import json
import shlex
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import hydra
import numpy as np
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, OmegaConf

from odmv.classical.reconstruct import CAPTURES
from odmv.cli import task_overrides
from odmv.config import compose_train
from odmv.io.atomic import write_json, write_text
from odmv.io.processes import run_child
from odmv.io.runfolder import (
    CONFIG,
    HELDOUT,
    METRICS,
    PREDICTIONS,
    PRIOR,
    ROBUSTNESS,
    SCENES_CSV,
    kept_copy,
)
from odmv.sim.shifts import parse_shift
from odmv.study.adapt import run_adaptation
from odmv.study.classical import classical_row
from odmv.study.figures import FIGURE_SCENES, pick_scenes
from odmv.study.heldout import HeldoutError, score_heldout
from odmv.study.prior import moves, prior_section, probe_run
from odmv.study.report import write_report
from odmv.study.results import Run
from odmv.study.robustness import SHIFTS, score_run
from odmv.study.summarize import summary_lines
from odmv.study.tables import own_width
from odmv.training.losses import OPTIONAL_TERMS, PHASE_TERMS
from odmv.training.module import OPTIMIZER, SCHEDULER

CLASSICAL_DIR = "classical"
STUDY = "study.md"  # the table of a study's own rows
RECORD = "reproduce.json"  # per row: the overrides that trained it and their key
# a row's record, with the predictions of the figures' scenes (checkpoints and logs stay behind)
KEPT = (METRICS, HELDOUT, ROBUSTNESS, PRIOR, RECORD, SCENES_CSV, CONFIG)
QUIET = ["trainer.enable_progress_bar=false", "data.progress=false"]  # a run's log is a file
RECORDERS = {
    "lightning.pytorch.callbacks.ModelCheckpoint",
    "lightning.pytorch.callbacks.LearningRateMonitor",
}


class ReproduceError(ValueError):
    """A one-line error about the reproduction's settings."""


@dataclass
class Job:
    overrides: list[str]  # train overrides beyond experiment=<protocol>
    seed: int
    folder: Path
    key: str  # hash of the resolved training config
    record: Path  # where its results are kept beside the report
    table: bool = False  # a row of the paper's tables
    rows: set[str] = field(default_factory=set)  # the study rows (labels) it is

    def result(self) -> Path | None:
        """The folder holding the row's test result: its run folder, else its record."""
        return finished(self.folder, self.record)

    def stale(self) -> bool:
        """Whether the row on disk was trained with another configuration than today's (its
        own saved config decides, else its recorded key: code that only adds settings leaves
        finished rows valid)."""
        key = trained_key(self.result() or self.folder)
        return key is not None and key != self.key

    def current(self) -> bool:
        """Whether the row has a result known to be of today's configuration."""
        done = self.result()
        return done is not None and trained_key(done) == self.key

    def interrupted(self) -> bool:
        """Whether the row's folder stopped before its end with a checkpoint of today's
        configuration (a row being trained again still has its old result in its record)."""
        ckpt = (self.folder / "checkpoints" / "last.ckpt").is_file()
        return ckpt and not finished(self.folder) and trained_key(self.folder) == self.key


def trained_key(folder: Path) -> str | None:
    """The key of the configuration that trained the row in ``folder``: from its saved config,
    else from its record; None for a record kept before either was written."""
    saved = folder / CONFIG
    if saved.is_file():
        return _run_key(OmegaConf.load(saved))
    record = folder / RECORD
    return json.loads(record.read_text()).get("key") if record.is_file() else None


def finished(*folders: Path) -> Path | None:
    """The first of ``folders`` that holds a test result (``metrics.json``), or None."""
    return next((f for f in folders if (f / METRICS).is_file()), None)


def sweep_overrides(protocol: str, table: str, extra: list[str]) -> list[list[str]]:
    """The jobs of one table's sweep (conf/sweep/<table>.yaml) as override lists, expanded like
    Hydra's basic sweeper (the cartesian product of the sweep's parameters)."""
    try:
        cfg = compose_train([f"experiment={protocol}", f"sweep={table}", *extra], hydra_cfg=True)
    except Exception as e:  # Hydra's composition errors name the missing option
        raise ReproduceError(f"protocol={protocol} table={table}: {e}") from None
    params = OmegaConf.to_container(cfg.hydra.sweeper.params, resolve=True)
    parsed = OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in params.items()])
    axes = []
    for o in parsed:
        key = o.get_key_element()
        values = o.sweep_string_iterator() if o.is_sweep_override() else [o.value()]
        axes.append([f"{key}={v}" for v in values])
    return [list(combo) for combo in itertools.product(*axes)]


def net_defaults(cls: type) -> dict:
    """The keyword defaults of net class ``cls``: a setting at its class's default builds the
    net as before the setting existed (one place for a net's defaults)."""
    return {
        k: list(p.default) if isinstance(p.default, tuple) else p.default
        for k, p in inspect.signature(cls).parameters.items()
        if p.default is not inspect.Parameter.empty
    }


def _run_key(cfg: DictConfig) -> str:
    """Hash of everything that shapes a run (not where it is written or what it is called)."""
    cfg = cfg.copy()
    cfg.paths.output_dir = "RUN"  # a run's own folder is not part of what it is
    d = OmegaConf.to_container(cfg, resolve=True)
    for k in (
        "paths",
        "task_name",
        "test",
        "ckpt_path",
        "resume",
        "log_images",
        "seeds",
        "contenders",
        "logger",
        "optimized_metric",
    ):
        d.pop(k, None)
    # this net's entry is in model.net / loss / optimizer; the other nets' are not this run's
    # (full_width reaches ODMV-Net's model.net only, so a baseline's row ignores it too)
    for per_net in ("widths", "alphas", "lrs", "full_width"):
        d.pop(per_net, None)
    for about in ("table2", "published_parameters", "display"):  # the registry's words on it
        d["model"].pop(about, None)
    net_class = hydra.utils.get_class(d["model"]["net"]["_target_"])
    # a loss setting the net has no output for is never read
    terms = set(net_class.LOSS_TERMS) | (set(PHASE_TERMS) if d.get("head") == "phase" else set())
    for term in (*OPTIONAL_TERMS, *PHASE_TERMS):
        if term not in terms:
            d["loss"].pop(term, None)
    callbacks = d.get("callbacks") or {}
    for name in [n for n, c in callbacks.items() if c.get("_target_") in RECORDERS]:
        callbacks.pop(name)  # where checkpoints go and how the rate is logged shape no weight
    # the paper's optimizer and schedule, named since they became configs: rows trained
    # before keep their keys
    for group, default in (("optimizer", OPTIMIZER), ("scheduler", SCHEDULER)):
        named = d.get(group) or {}
        if named.get("_target_") == default:
            named.pop("_target_")
            named.pop("_partial_", None)
            if named.get("interval") == "epoch":
                named.pop("interval")
    if not d.get("adapt"):  # label-free adaptation off: its settings are never read
        d.pop("adapt", None)
        d.pop("adaptation", None)
    if not d.get("distill_from"):  # no teacher: its weights are never read
        d.pop("distill", None)
    net = d["model"]["net"]
    for key, default in net_defaults(net_class).items():  # as before the setting was
        if key in net and net[key] == default:
            net.pop(key)
    if d["data"].get("labels") is True:  # the ground truth read, as before it could be not
        d["data"].pop("labels")
    for setting in QUIET:  # how a run reports is not what it is
        group, _, key = setting.partition("=")[0].rpartition(".")
        d[group].pop(key, None)
    d = _without_nulls(d)
    return hashlib.sha1(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:8]


def _without_nulls(d):
    """``d`` without its null settings: a setting added with a null default (its off state)
    leaves the rows trained before it valid, while any value set is part of the key."""
    if isinstance(d, dict):
        return {k: _without_nulls(v) for k, v in d.items() if v is not None}
    if isinstance(d, list):
        return [_without_nulls(v) for v in d]
    return d


def _table_rows(protocol: str, tables: list[str], extra: list[str], seed: int):
    """(name, overrides, config) of each row of the tables' sweeps at ``seed``, named by what
    the row is (net, views, Table I row, a width of its own)."""
    for table in tables:
        for ov in sweep_overrides(protocol, table, extra):
            ov = [o for o in ov if not o.startswith("seed=")] + [f"seed={seed}"]
            cfg = compose_train([f"experiment={protocol}", *extra, *ov])
            name = f"{cfg.model.name}-s{len(cfg.data.views)}"
            if cfg.model.name == "odmvnet":
                name += f"-{cfg.ablation}"
            if own_width(cfg) is not None:
                name += f"-w{own_width(cfg)}"  # a row at another width than the protocol's
            yield f"{name}-seed{seed}", ov, cfg


def _study_rows(protocol: str, rows: dict, extra: list[str], seed: int):
    """(name, overrides, config) of each of a study's own rows (NAME: [override, ...]) at
    ``seed``; ``{seed}`` in an override is the seed (``init_from=RUNS/base-seed{seed}``: each
    seed fine-tunes its own base run)."""
    for label, overrides in rows.items():
        ov = [*(o.replace("{seed}", str(seed)) for o in overrides), f"seed={seed}"]
        try:
            cfg = compose_train([f"experiment={protocol}", *extra, *ov])
        except Exception as e:  # Hydra's composition errors name the bad override
            raise ReproduceError(f"rows.{label}: {e}") from None
        yield label, f"{label}-seed{seed}", ov, cfg


def plan(
    protocol: str,
    tables: list[str],
    seeds: list[int] | None,
    extra: list[str],
    runs_dir: Path,
    records: Path | None = None,
    rows: dict | None = None,
) -> list[Job]:
    """Every distinct run of the reproduction (the tables' rows, then a study's own ``rows``),
    seed-major, each with its folder (named by the row; a configuration that two rows share is
    one run) and its record in ``records``."""
    records = runs_dir / "records" if records is None else records
    base = compose_train([f"experiment={protocol}", *extra])
    seeds = list(base.seeds) if seeds is None else list(seeds)
    jobs: dict[str, Job] = {}
    for seed in seeds:
        found = [
            *((None, *r) for r in _table_rows(protocol, tables, extra, seed)),
            *_study_rows(protocol, rows or {}, extra, seed),
        ]
        for label, name, ov, cfg in found:
            key = _run_key(cfg)
            job = jobs.setdefault(key, Job(ov, seed, runs_dir / name, key, records / name))
            if label is None:
                job.table = True
            else:
                job.rows.add(label)
            taken = next((j for j in jobs.values() if j.folder.name == name), job)
            if taken is not job:
                raise ReproduceError(
                    f"{name}: two rows would share this folder ({' '.join(taken.overrides)}"
                    f" and {' '.join(ov)}); give one of them its own setting"
                )
    return list(jobs.values())


def _train(job: Job, protocol: str, extra: list[str], train: list[str]) -> dict:
    """Train one row in a subprocess, ``train`` and its overrides (a clean process per run);
    its log goes to train.out. An interrupted row of today's configuration continues from its
    last checkpoint."""
    tmp = job.folder.with_name(f".{job.folder.name}.log")
    tmp.parent.mkdir(parents=True, exist_ok=True)
    if job.interrupted():
        print(f"    continuing from {job.folder / 'checkpoints' / 'last.ckpt'}", flush=True)
        # hydra.output_subdir=null: the run's own .hydra/config.yaml stays as it was
        args = [f"resume={job.folder}", "hydra.output_subdir=null", *QUIET]
        if (job.folder / "train.out").is_file():  # its log goes on in the same file
            (job.folder / "train.out").replace(tmp)
    else:
        if job.folder.exists():
            shutil.rmtree(job.folder)
        tmp.unlink(missing_ok=True)
        args = [f"experiment={protocol}", *extra, *job.overrides, *QUIET]
    cmd = [*train, *args, f"hydra.run.dir={job.folder}"]
    with tmp.open("a") as log:
        log.write(" ".join(cmd) + "\n")
        log.flush()
        proc = run_child(cmd, log)
    if job.folder.is_dir():
        tmp.replace(job.folder / "train.out")
    if proc.returncode != 0 or not (job.folder / METRICS).is_file():
        where = job.folder / "train.out" if job.folder.is_dir() else tmp
        raise ReproduceError(f"{where}: training failed (exit {proc.returncode})")
    record = {"overrides": [f"experiment={protocol}", *extra, *job.overrides], "key": job.key}
    write_json(job.folder / RECORD, record)
    return json.loads((job.folder / METRICS).read_text())


def keep(folder: Path, record: Path) -> bool:
    """Copy a finished run's results into ``record`` (replaced whole, never half-written);
    of its test predictions only the scenes the report's figures show, so a record stays small
    at any resolution. Returns whether anything changed: nothing for an unfinished run, and an
    unchanged record (the same figures of the same configuration) is not rewritten, so a
    committed one stays as it is."""
    if not finished(folder):
        return False
    metrics = (folder / METRICS).read_text()
    _merge_robustness(folder, record)
    if (
        trained_key(record) == trained_key(folder)
        and _text(record / METRICS) == metrics
        and all(
            _text(record / name) == _text(folder / name) for name in (HELDOUT, ROBUSTNESS, PRIOR)
        )
    ):
        return False
    tmp = record.with_name(f".{record.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    for name in KEPT:
        if (folder / name).is_file():
            (tmp / name).parent.mkdir(parents=True, exist_ok=True)
            kept_copy(folder / name, tmp / name)
    if (folder / PREDICTIONS).is_file():
        shown = set(pick_scenes(Run(folder, json.loads(metrics)), FIGURE_SCENES))
        with np.load(folder / PREDICTIONS) as z:
            pick = np.isin(z["scene_id"], list(shown))
            np.savez_compressed(tmp / PREDICTIONS, **{k: z[k][pick] for k in z.files})
    if record.exists():
        gone = record.with_name(f".{record.name}.old")
        shutil.rmtree(gone, ignore_errors=True)
        record.rename(gone)
        tmp.rename(record)
        shutil.rmtree(gone)
    else:
        record.parent.mkdir(parents=True, exist_ok=True)
        tmp.rename(record)
    return True


def _merge_robustness(folder: Path, record: Path) -> None:
    """Robustness scores of the same training result (the same ``metrics.json``) that only
    the record holds (``odmv.study robustness`` scores a committed record in place) are added
    to the run folder's, so keeping the run never drops them."""
    kept, own = record / ROBUSTNESS, folder / ROBUSTNESS
    if not kept.is_file() or _text(record / METRICS) != _text(folder / METRICS):
        return
    scores = json.loads(own.read_text()) if own.is_file() else {}
    extra = {k: v for k, v in json.loads(kept.read_text()).items() if k not in scores}
    if extra:
        write_json(own, scores | extra)


def _text(path: Path) -> str | None:
    return path.read_text() if path.is_file() else None


def _interior(m: dict) -> str:
    """ ", interior X mm" where the record has the interior MAE (odmv.training.metrics)."""
    v = m.get("test/mae_mm_interior")
    return "" if v is None else f", interior {v:.4f} mm"


def classical_rows(dm, runs_dir: Path, records: Path) -> list[Path]:
    """The classical reference on the test scenes: the full sequences, then the same pipeline
    on fewer images per projector down to the one a network sees (the last capture is the full
    row itself); each kept as a record. Returns their result folders."""
    folders = []
    for capture in (None, *CAPTURES[:-1]):
        name = CLASSICAL_DIR if capture is None else capture.name
        classical, kept = runs_dir / name, records / name
        if not finished(classical, kept):
            what = capture.label if capture else "phase shifting, full sequences"
            print(f"classical reference ({what}, 4 projectors) on the test scenes", flush=True)
            classical_row(dm.root, classical, resolution=dm.resolution, capture=capture)
        keep(classical, kept)
        folders.append(finished(classical, kept))
    return folders


#: the classical method's figures on the probe's moved twins, shared by a call's rows
_PROBE_CACHE: dict = {}


def score(job: Job, threads: int | None, cfg: DictConfig) -> None:
    """Score a finished row on the held-out set and, where ``robustness.rows`` names it, on the
    shifted twins, once each, while its checkpoint is on disk."""
    if cfg.heldout and not (job.folder / HELDOUT).is_file():
        held = score_heldout(job.folder, threads, cfg.heldout)
        print(
            f"    held-out MAE {held['test/mae_mm']:.4f} mm "
            f"(shadowed {held['test/mae_mm_shadowed']:.4f} mm{_interior(held)})",
            flush=True,
        )
    rob = cfg.get("robustness") or {}
    if any(fnmatch.fnmatch(job.folder.name, p) for p in rob.get("rows") or []):
        shifts = [parse_shift(s) for s in (rob.get("shifts") or SHIFTS)]
        score_run(job.folder, shifts, rob.get("scenes", 100), threads)
    if cfg.get("prior") and not (job.folder / PRIOR).is_file():
        r = probe_run(job.folder, moves(), threads, classical=True, cache=_PROBE_CACHE)
        five = next(m for m in r["moves"] if m["offset_mm"] == 5.0)
        print(
            f"    prior probe: MAE x{five['ratio_mae_mm']:.2f} with the scene 5 mm farther, "
            f"slope {r['slope_mm_per_mm']:+.4f} mm/mm",
            flush=True,
        )


def run_study(cfg: DictConfig, train: list[str]) -> Path:
    """Run (or continue) the reproduction or study of ``cfg`` (conf/reproduce.yaml), each row
    trained by the command ``train`` (the training app); returns the report folder."""
    protocol, extra = cfg.protocol, list(cfg.overrides or [])
    runs_dir, out, records = Path(cfg.runs_dir), Path(cfg.out), Path(cfg.records)
    t0 = time.perf_counter()
    jobs = plan(protocol, list(cfg.tables), cfg.seeds, extra, runs_dir, records, cfg.rows)
    base = compose_train([f"experiment={protocol}", *extra])
    dm = hydra.utils.instantiate(base.data, _convert_="all")
    dm.prepare_data()  # renders the protocol's dataset once; every row reads it
    threads = base.get("threads")
    classical = classical_rows(dm, runs_dir, records) if cfg.classical else []
    for job in jobs:  # rows finished before they were kept (or by hand) are kept now
        if finished(job.folder) and job.current():
            try:
                score(job, threads, cfg)
            except HeldoutError as e:  # its checkpoint is gone: the row keeps its test result
                print(f"note: {e}", flush=True)
        if keep(job.folder, job.record):
            print(f"kept {job.folder.name} in {job.record}", flush=True)
    retrain = list(cfg.retrain)
    again = [j for j in jobs if any(fnmatch.fnmatch(j.folder.name, p) for p in retrain)]
    todo = [j for j in jobs if not j.result() or (j in again and not j.current())]
    for job in jobs:
        if job.stale() and job not in todo:
            print(
                f"note: {job.folder.name} was trained with another configuration than today's; "
                f"it is kept (retrain=[{job.folder.name}] trains it again)",
                flush=True,
            )
    print(
        f"protocol {protocol}: {len(jobs)} runs ({len(jobs) - len(todo)} done"
        + (f", {len([j for j in todo if j.result()])} to train again" if again else "")
        + "), "
        f"dataset {dm.root}, runs in {runs_dir}",
        flush=True,
    )
    for k, job in enumerate(todo, 1):
        print(f"[{k}/{len(todo)}] {job.folder.name}: {' '.join(job.overrides)}", flush=True)
        m = _train(job, protocol, extra, train)
        score(job, threads, cfg)
        keep(job.folder, job.record)
        print(
            f"    {m['train_seconds'] / 60:.1f} min, test MAE {m['test/mae_mm']:.4f} mm "
            f"(shadowed {m['test/mae_mm_shadowed']:.4f} mm{_interior(m)})",
            flush=True,
        )
    if cfg.get("adapt"):  # label-free adaptation of finished runs (odmv.study.adapt)
        given = task_overrides() or [f"protocol={protocol}", "study=adapt"]
        command = "python -m odmv.reproduce " + " ".join(shlex.quote(o) for o in given)
        run_adaptation(cfg.adapt, runs_dir, out, threads, train, command)
    rows = dict(cfg.rows or {})
    if rows:  # a study's own rows: one table of them, each row's seeds together
        groups = [(label, [j.result() for j in jobs if j.rows & {label}]) for label in rows]
        probed = prior_section([f for _, fs in groups for f in fs if f is not None])
        write_text(out / STUDY, "\n".join(summary_lines(groups) + ["", *probed]).rstrip() + "\n")
        print(f"study: {out / STUDY}", flush=True)
    if not cfg.tables:
        return out
    folders = [j.result() for j in jobs if j.table] + classical
    write_report(folders, out, protocol=protocol)
    minutes = (time.perf_counter() - t0) / 60
    print(f"report: {out / 'tables.md'} (this call: {minutes:.1f} min)")
    return out
