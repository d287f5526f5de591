"""A training run from a composed config, as ``python -m odmv.train`` runs it: the data
module, module and trainer (:func:`build`, shared with evaluation), fitting and testing the
best checkpoint into the run folder (``metrics.json``, ``metrics.csv``), a stop said in one
line with how to resume, and the checks on which folder a run may write into."""

from __future__ import annotations

import json
import shutil
import signal
import sys
from pathlib import Path

import hydra
import lightning as L
import torch
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf

from odmv.cli import (
    STOPPED,
    Interrupted,
    in_multirun,
    rank_zero_print,
    set_threads,
    sigterm_deferred,
    task_overrides,
    tool,
)
from odmv.io.atomic import write_json, write_text
from odmv.io.runfolder import CONFIG, METRICS, portable, portable_record
from odmv.training.checkpoint import (
    AtomicCheckpointIO,
    check_fits,
    check_weights,
    initial_weights,
    read_checkpoint,
)
from odmv.training.configs import check_numbers, data_config, run_folder_of
from odmv.training.ema import WeightEMA
from odmv.training.fine_tune import prepare_adaptation
from odmv.training.module import FPPModule
from odmv.training.pace import CpuPace, EpochLine, busy_cores_note, heavy_on_cpu
from odmv.training.provenance import provenance, training_setup
from odmv.training.runlock import RunFolderError, check_new_run, holding
from odmv.training.sweep import append_row


def build(cfg: DictConfig):
    """Data module, module, trainer from a composed config (shared with evaluation)."""
    check_numbers(cfg)
    dm = hydra.utils.instantiate(data_config(cfg), _convert_="all")
    module = FPPModule.from_config(cfg)
    loggers = [hydra.utils.instantiate(c) for c in (cfg.get("logger") or {}).values()]
    callbacks = [hydra.utils.instantiate(c) for c in (cfg.get("callbacks") or {}).values()]
    if cfg.get("ema") is not None:
        callbacks.append(WeightEMA(cfg.ema))
    if heavy_on_cpu(cfg, str(cfg.trainer.get("accelerator", "auto"))):
        callbacks.append(CpuPace(cfg))
    # Lightning's bar is for a terminal; a log file (nohup, a study, tee) gets one line an epoch
    bar = bool(cfg.trainer.get("enable_progress_bar", True)) and sys.stdout.isatty()
    if not bar:
        callbacks.append(EpochLine())
    trainer = hydra.utils.instantiate(
        cfg.trainer,
        logger=loggers or False,
        callbacks=callbacks,
        plugins=[AtomicCheckpointIO()],
        enable_progress_bar=bar,
    )
    return dm, module, trainer


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit, then test the best checkpoint; returns the test metrics (mm). Continuing from a
    checkpoint in a run folder (``ckpt_path=RUN/checkpoints/last.ckpt``) continues that
    folder: its TensorBoard and CSV logs, and its best checkpoint."""
    set_threads(cfg.get("threads"))
    check_numbers(cfg)
    if str(cfg.trainer.get("accelerator", "auto")) == "cpu" or not torch.cuda.is_available():
        note = busy_cores_note(torch.get_num_threads())
        if note:
            rank_zero_print(note)
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    ckpt = read_checkpoint(cfg.ckpt_path) if cfg.ckpt_path else None
    continuing = ckpt is not None and (run := run_folder_of(cfg.ckpt_path)) is not None
    if continuing and not cfg.get("resume"):
        refuse_finished(cfg.ckpt_path, run)
    if continuing:
        cfg.paths.output_dir = str(run)
        rank_zero_print(f"continuing {run} from epoch {ckpt.get('epoch', 0) + 1}")
    out_dir = Path(cfg.paths.output_dir)
    if not continuing:
        check_new_run(out_dir)
    with holding(out_dir):
        return _fit_and_test(cfg, ckpt, out_dir)


def _fit_and_test(cfg: DictConfig, ckpt: dict | None, out_dir: Path) -> dict[str, float]:
    fine_tune = cfg.get("adapt") or (cfg.get("adaptation") or {}).get("supervised")
    # without Hydra's app (the demo, scripts) none is there; a fine-tune's is the command
    # line's, while resume=RUN needs the one it ran (the user's data, the autos resolved)
    if not (out_dir / CONFIG).is_file() or (fine_tune and ckpt is None):
        write_text(out_dir / CONFIG, OmegaConf.to_yaml(cfg))
    dm, module, trainer = build(cfg)
    dm.check_splits(bool(cfg.test) and not fine_tune)  # a user's scenes may all adapt
    if ckpt is not None:
        check_fits(cfg.ckpt_path, ckpt, module.hparams.net_cfg, list(dm.views))
        check_weights(cfg.ckpt_path, ckpt["state_dict"], module.state_dict())
    elif cfg.get("init_from"):  # a resumed fine-tune continues from its own checkpoint instead
        module.load_state_dict(initial_weights(cfg.init_from, module.state_dict()))
    calibration = {}
    if cfg.get("adapt"):  # before adapting: the data, then the fit and the calibration check
        calibration = prepare_adaptation(cfg, dm, module, ckpt is not None, out_dir)
    try:
        with sigterm_deferred():
            trainer.fit(module, datamodule=dm, ckpt_path=cfg.ckpt_path, weights_only=True)
    except SIGTERMException:  # Lightning's is a SystemExit without a status: exit 0
        raise _interrupted(out_dir, trainer, signal.SIGTERM) from None
    except SystemExit:  # Lightning ends a Ctrl-C with exit(1) after its graceful shutdown
        if not trainer.interrupted:
            raise
        raise _interrupted(out_dir, trainer, signal.SIGINT) from None
    train_seconds = module.train_seconds()  # a resumed run's included
    if trainer.is_global_zero:  # DDP: one process writes the run's files
        dm.save_split(out_dir / "split.json")
    metrics: dict = {}
    optimized = cfg.get("optimized_metric")
    if optimized:
        metrics[optimized] = best_value(trainer, optimized)
    if cfg.test:
        best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
        module.test_dir = out_dir
        if dm.splits.get("test") or not fine_tune:  # a user's scenes may all adapt
            results = trainer.test(
                module,
                datamodule=dm,
                ckpt_path=best or None,
                weights_only=True,
                verbose=False,  # the closing lines say the main figures, metrics.json all
            )
            metrics.update({k: float(v) for k, v in results[0].items()})
        if fine_tune:
            metrics.update(adapted_from=portable(cfg.init_from), **calibration)
        overrides = task_overrides()
        metrics.update(
            best_checkpoint=best,
            train_seconds=round(train_seconds, 1),
            epochs=trainer.current_epoch,
            parameters=sum(p.numel() for p in module.net.parameters()),
            width=cfg.model.net.get("base_width"),
            model=cfg.model.name,
            views=list(dm.spec.views),
            ablation=cfg.get("ablation"),
            head=cfg.get("head") or "depth",
            seed=cfg.seed,
            # floating-point sums split by thread count: the same seed on another count is
            # another run (experiments/results/accuracy/notebook.md, "Repeatability")
            threads=torch.get_num_threads(),
            overrides=" ".join(overrides),
            setup=training_setup(cfg),  # what a row's seeds must share (odmv.study.results)
            **provenance(dm.root),
        )
        if trainer.is_global_zero:
            record = portable_record(metrics, out_dir)
            write_json(out_dir / METRICS, record)
            append_row(
                out_dir / "metrics.csv",
                {k: v for k, v in record.items() if not isinstance(v, (list, dict))},
            )
    return metrics


def _interrupted(out_dir: Path, trainer: L.Trainer, sig: signal.Signals) -> Interrupted:
    name = "Ctrl-C" if sig == signal.SIGINT else sig.name
    if not (out_dir / "checkpoints" / "last.ckpt").is_file():  # the folder goes with the stop
        return Interrupted(
            f"stopped by {name} before the first epoch ended (while the data was prepared or "
            f"the epoch ran); nothing to resume: {STOPPED} (a dataset being rendered continues "
            "where it stopped)",
            sig,
        )
    return Interrupted(
        f"{out_dir}: stopped by {name} in epoch {trainer.current_epoch}; resume={out_dir} "
        "continues from the last finished epoch (checkpoints/last.ckpt)",
        sig,
    )


def best_value(trainer: L.Trainer, name: str) -> float:
    """The best value of a logged metric over the run: the checkpoint callback's best score
    when it monitors ``name``, else the value at the last epoch."""
    checkpoint = trainer.checkpoint_callback
    if checkpoint is not None and checkpoint.monitor == name and checkpoint.best_model_score:
        return float(checkpoint.best_model_score)
    if name not in trainer.callback_metrics:
        logged = ", ".join(sorted(trainer.callback_metrics)) or "none"
        raise ValueError(f"optimized_metric: {name} was not logged (logged: {logged})")
    return float(trainer.callback_metrics[name])


class Metrics(dict):
    """A run's metrics that a sweeper reads as one number: the value of ``optimized_metric``."""

    def __init__(self, metrics: dict, optimized: str | None):
        super().__init__(metrics)
        self.optimized = optimized

    def __float__(self) -> float:
        if not self.optimized:
            raise TypeError("optimized_metric is not set: nothing for a sweeper to optimize")
        return float(self[self.optimized])


def test_line(metrics: dict) -> str:
    """The test split's main figures in a line: MAE and RMSE over all pixels, on the interior
    and the edge band, and on the shadowed pixels, where the record has them."""
    shown = [f"MAE {metrics['test/mae_mm']:.4f} mm", f"RMSE {metrics['test/rmse_mm']:.4f} mm"]
    for key, name in (("interior", "interior"), ("edge", "edge band"), ("shadowed", "shadowed")):
        if f"test/mae_mm_{key}" in metrics:
            shown.append(f"{name} MAE {metrics[f'test/mae_mm_{key}']:.4f} mm")
    return ", ".join(shown)


def refuse_finished(ckpt_path, run: Path) -> None:
    """``ckpt_path=`` of a finished run's checkpoint would train that run again in place."""
    if (run / METRICS).is_file():
        raise RunFolderError(
            f"ckpt_path={ckpt_path}: {run} holds a finished run, which this would train "
            f"again in place; train it further with resume={run} trainer.max_epochs=N, or "
            f"start a new run from its weights with init_from={run}"
        )


def check_continued_folder(cfg: DictConfig, overrides: list[str]) -> None:
    """``ckpt_path=`` of a checkpoint in a run folder continues that folder; refused where the
    command names another folder for the run (it would write where it was not pointed)."""
    # where the run writes: paths.output_dir where named, else Hydra's folder where named
    named = [o for o in overrides if o.startswith("paths.output_dir=")] or [
        o for o in overrides if o.startswith("hydra.run.dir=")
    ]
    run = run_folder_of(cfg.ckpt_path) if cfg.get("ckpt_path") else None
    if cfg.get("resume") or run is None:
        return
    refuse_finished(cfg.ckpt_path, run)
    if not named:
        return
    if Path(named[-1].split("=", 1)[1]).resolve() != run:
        raise RunFolderError(
            f"ckpt_path={cfg.ckpt_path} continues the run in {run}, not {named[-1]}; continue "
            f"it with resume={run}, or start a new run from its weights with "
            f"init_from={run}"
        )


def adopt_hydra_files(hydra_dir: Path, out: Path) -> None:
    """A run written elsewhere than Hydra's folder (``paths.output_dir=DIR``) takes Hydra's
    ``.hydra/`` (its config, which ``resume=DIR`` reads) unless it has its own (a resumed run);
    the folder Hydra made is then removed when the run ends."""
    source, target = hydra_dir / ".hydra", out / ".hydra"
    if out.resolve() == hydra_dir.resolve() or not source.is_dir():
        return
    if target.exists():
        if (out / METRICS).is_file() or any((out / "checkpoints").glob("*.ckpt")):
            return  # a run's own config (resumed, or refused as another run's by train)
        shutil.rmtree(target)  # a failed run's, which left nothing else
    out.mkdir(parents=True, exist_ok=True)
    shutil.move(source, target)


def check_launch(cfg: DictConfig) -> None:
    """Refuse a multirun of multi-process DDP jobs in one process tree: each job's ranks would
    be started by a job of the sweep (use a cluster launcher, docs/training.md)."""
    from hydra.core.hydra_config import HydraConfig

    if not in_multirun():
        return
    strategy, devices = str(cfg.trainer.get("strategy", "")), cfg.trainer.get("devices", 1)
    local = "BasicLauncher" in str(HydraConfig.get().launcher.get("_target_", ""))
    if strategy.startswith("ddp") and devices not in (1, "1") and local:
        raise ValueError(
            "trainer=ddp: not with -m on the local launcher; sweep on SLURM with "
            "hydra/launcher=slurm, or run the jobs one at a time"
        )


def next_steps(run: Path, ckpt: Path) -> list[str]:
    """The commands that continue from a finished run folder, each with its real paths: a
    prediction of its first test scene, evaluation, export to ONNX and a report."""
    split = json.loads((run / "split.json").read_text())
    scene = Path(split["root"]) / "scenes" / split["test"][0]
    py = f"{tool('python')} -m"
    return [
        f"{py} odmv.predict ckpt_path={ckpt} input={scene} out={run / 'prediction'}",
        f"{py} odmv.evaluate ckpt_path={ckpt} paths.output_dir={run / 'evaluation'}",
        f"{py} odmv.export ckpt_path={ckpt} out={run / 'onnx'}",
        f"{py} odmv.report runs=[{run}] out={run / 'report'}",
    ]
