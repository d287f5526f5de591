"""Train a net: ``python -m odmv.train model=odmvnet views=4`` (config: conf/train.yaml).

A thin Hydra wrapper around :func:`train`, which tests call with a composed config. After
fitting it tests the best checkpoint and writes ``metrics.json`` and ``metrics.csv`` (one row
with the run's overrides) into the run folder; multiruns also collect every job into
``results.csv`` in the sweep folder (odmv.training.sweep).
"""

from __future__ import annotations

import json
import shutil
import signal
import sys
import time
from dataclasses import replace
from pathlib import Path

import hydra
import lightning as L
import numpy as np
import torch
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf

from odmv.classical.row import classical_depths
from odmv.cli import (
    STOPPED,
    Interrupted,
    JobFailed,
    app,
    in_multirun,
    rank_zero_print,
    remove_if_empty,
    run_app,
    set_threads,
    sigterm_deferred,
    task_overrides,
    tool,
)
from odmv.data.dataset import matching_fringe
from odmv.io.atomic import write_json, write_text
from odmv.io.manifest import MANIFEST, load_manifest
from odmv.io.runfolder import (
    CALIBRATION_CHECK,
    CONFIG,
    METRICS,
    portable,
    portable_record,
    recorded_dataset,
)
from odmv.rig import whole_number
from odmv.training.adaptation import (
    CHECK_SOURCES,
    adaptation_lines,
    check_calibration,
    second_harmonic_share,
    view_offsets,
)
from odmv.training.checkpoint import (
    AtomicCheckpointIO,
    check_fits,
    check_weights,
    checkpoint_path,
    initial_weights,
    read_checkpoint,
)
from odmv.training.consistency import (
    SECOND_HARMONIC_SHARE,
    chosen_fit,
    resolved_adaptation,
    target_for,
)
from odmv.training.ema import WeightEMA
from odmv.training.module import FPPModule, load_module
from odmv.training.pace import CpuPace, EpochLine, busy_cores_note, heavy_on_cpu
from odmv.training.provenance import provenance, training_setup
from odmv.training.runlock import RunFolderError, check_new_run, check_not_held, holding
from odmv.training.sweep import append_row


def data_config(cfg: DictConfig) -> dict:
    """The resolved data settings with absolute dataset and cache folders, so a checkpoint
    finds its dataset from any working directory."""
    data = OmegaConf.to_container(cfg.data, resolve=True)
    for key in ("root", "cache_dir"):
        if data.get(key) is not None:
            data[key] = str(Path(data[key]).resolve())
    return data


def run_summary(cfg: DictConfig) -> dict:
    """The settings that tell runs apart, for TensorBoard's HPARAMS tab (the module adds the
    resolved views, normalization and parameter count)."""
    return {
        "model": cfg.model.name,
        "ablation": cfg.get("ablation"),
        "seed": cfg.seed,
        "width": cfg.model.net.get("base_width"),
        "lr": cfg.optimizer.lr,
        "batch_size": cfg.data.batch_size,
        "resolution": str(cfg.data.resolution),
        "max_epochs": cfg.trainer.max_epochs,
        "norm": cfg.get("norm"),
        "reference": str(cfg.get("reference")),
        "stem_stride": cfg.get("stem_stride"),
        "depth_target": cfg.data.get("depth_target"),
        "precision": str(cfg.trainer.precision),
        "ema": cfg.get("ema"),
        "distill_from": cfg.get("distill_from"),
    }


def check_numbers(cfg: DictConfig) -> None:
    """The whole-number settings a run needs, each refused by name before anything starts."""
    whole_number(cfg.seed, "seed", 0, "a seed is 0 or more")
    whole_number(cfg.data.batch_size, "data.batch_size", 1, "at least 1")
    epochs = cfg.trainer.get("max_epochs")
    what = "at least 1 (or -1 with trainer.max_steps)"
    if epochs is not None and whole_number(epochs, "trainer.max_epochs", -1, what) == 0:
        raise ValueError(f"trainer.max_epochs=0: {what}")


def build(cfg: DictConfig):
    """Data module, module, trainer from a composed config (shared with evaluation)."""
    check_numbers(cfg)
    data_cfg = data_config(cfg)
    dm = hydra.utils.instantiate(data_cfg, _convert_="all")
    module = FPPModule(
        net_cfg=OmegaConf.to_container(cfg.model.net, resolve=True),
        loss=OmegaConf.to_container(cfg.loss, resolve=True),
        optimizer=OmegaConf.to_container(cfg.optimizer, resolve=True),
        scheduler=OmegaConf.to_container(cfg.scheduler, resolve=True),
        log_images=cfg.log_images,
        data_cfg=data_cfg,
        run_info=run_summary(cfg),
        compile=cfg.get("compile"),
        adapt=adapt_settings(cfg),
        distill=distill_settings(cfg),
    )
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


def adapt_settings(cfg: DictConfig) -> dict | None:
    """``adapt=true``: the adaptation settings and the checkpoint it starts from (``base``)."""
    if not cfg.get("adapt"):
        return None
    return OmegaConf.to_container(cfg.adaptation, resolve=True) | {"base": str(cfg.init_from)}


def distill_settings(cfg: DictConfig) -> dict | None:
    """``distill_from=RUN`` (a checkpoint, or a finished run folder: its best checkpoint): the
    teacher's checkpoint and the weights of its outputs (``distill``)."""
    source = cfg.get("distill_from")
    if not source:
        return None
    path = checkpoint_path(source)
    if not path.is_file():
        raise ValueError(f"distill_from: {source}: no such checkpoint or run folder")
    return OmegaConf.to_container(cfg.distill, resolve=True) | {"teacher": str(path.resolve())}


def run_folder_of(ckpt_path: str | Path) -> Path | None:
    """The run folder a checkpoint was saved in (``RUN/checkpoints/*.ckpt``), if any."""
    folder = Path(ckpt_path).resolve().parent
    is_run = folder.name == "checkpoints" and (folder.parent / ".hydra").is_dir()
    return folder.parent if is_run else None


def resumed_config(cfg: DictConfig, overrides: list[str]) -> DictConfig:
    """``resume=RUN``: the run's own config, continuing from its last checkpoint; other
    ``key=value`` overrides on the command line (e.g. trainer.max_epochs=80) apply on top."""
    run = Path(cfg.resume).resolve()
    saved = run / ".hydra" / "config.yaml"
    if not saved.is_file():
        raise ValueError(f"resume: {run}: not a run folder (no .hydra/config.yaml)")
    out = _moved_targets(OmegaConf.load(saved))
    _override(out, cfg, overrides, ("resume", "ckpt_path"), f"the run in {run}", "resume")
    out.ckpt_path = str(run / "checkpoints" / "last.ckpt")
    out.resume = str(run)  # continued on purpose: a finished run may be trained further
    return out


def _override(out: DictConfig, cfg: DictConfig, overrides, skip, what: str, app: str) -> None:
    """Apply the command line's ``key=value`` overrides (but ``skip``) to a saved config."""
    for override in overrides:
        key, _, value = override.partition("=")
        if key.lstrip("+~") in skip or "=" not in override:
            continue
        if OmegaConf.select(out, key, default=_MISSING) is _MISSING:
            raise ValueError(
                f"{app}: {key} is not a setting of {what} (it keeps that run's config groups)"
            )
        OmegaConf.update(out, key, cfg_value(cfg, key, value), merge=False)


#: what ``adapt=true`` takes from the command line rather than from the run it adapts
_ADAPT_OWN = ("adapt", "init_from", "root", "data", "seed", "threads", "test")


def adapted_config(cfg: DictConfig, overrides: list[str]) -> DictConfig:
    """``adapt=true init_from=RUN root=DATASET``: RUN's own config (its net, input and data
    settings, so the adapted net reads images as RUN's did) pointed at DATASET's fringes with
    no labels read, starting from RUN's best checkpoint, trained by ``adaptation``'s settings
    with the best epoch chosen by the held-out scenes' label-free loss; other ``key=value``
    overrides apply on top. ``adaptation.supervised=true``: the same fine-tune with DATASET's
    depth and RUN's own loss instead, the best epoch by val/mae_mm (the ceiling)."""
    if not cfg.get("init_from"):
        raise ValueError("adapt: init_from=RUN names the trained run to adapt")
    source = Path(cfg.init_from).resolve()
    run = source if source.is_dir() else run_folder_of(source)
    saved = run / ".hydra" / "config.yaml" if run is not None else None
    if saved is None or not saved.is_file():
        raise ValueError(f"init_from: {source}: not a run folder (no .hydra/config.yaml)")
    ckpt = checkpoint_path(source)
    root = cfg.get("root")
    if not root:
        raise ValueError("adapt: root=DATASET names the fringe images to adapt to")
    adaptation = OmegaConf.to_container(cfg.adaptation, resolve=True)
    user = load_manifest(root)
    images = user.images if adaptation["target"] == "auto" else None
    a = OmegaConf.create(resolved_adaptation(adaptation, images))
    # the user's image of the fringe the net was trained on (full sequences hold them all)
    net = read_checkpoint(ckpt)["hyper_parameters"]
    fringe = matching_fringe(user, net.get("input_spec") or {}, net.get("views") or [], root)
    out = _moved_targets(OmegaConf.load(saved))
    out.paths = OmegaConf.to_container(cfg.paths, resolve=True)
    # the dataset: read, never rendered; without its ground truth (its files may be absent)
    # unless this is the supervised fine-tune that adaptation is measured against
    data = {"root": str(Path(root).resolve()), "render": False, "labels": bool(a.supervised)}
    data |= {"fringe_frequency": fringe[0], "fringe_step": fringe[1]}
    data |= {"calibration": True, "val_from_train": a.val_share}  # the loss needs the maps
    # classical targets are per scene, as stored: none turned; auto as well (how it was measured)
    if adaptation["target"] != "fringes":
        data["augment"] = None
    if a.replay and not a.supervised:  # the run's own training scenes, as it read them
        own = OmegaConf.to_container(out.data, resolve=True) | {"calibration": True}
        own["root"] = str(recorded_dataset({"dataset": own["root"]}, run))  # from any folder
        if not (Path(own["root"]) / MANIFEST).is_file():
            raise ValueError(
                f"adaptation.replay: {own['root']}: the twin that {run} was trained on is not "
                "here (no manifest.json); render it again, or adaptation.replay=0 to adapt "
                "without it"
            )
        data["replay"] = {k: v for k, v in own.items() if k != "_target_"} | {"render": False}
    OmegaConf.update(out, "data", data, merge=True)
    out.root = data["root"]
    out.adapt, out.adaptation = not a.supervised, OmegaConf.to_container(a, resolve=True)
    out.init_from, out.ckpt_path, out.resume = str(ckpt), None, None
    out.seed, out.test = cfg.seed, cfg.test
    out.threads = cfg.get("threads") if cfg.get("threads") is not None else out.get("threads")
    out.trainer.max_epochs, out.optimizer.lr = a.epochs, a.lr
    if "T_0" in (out.get("scheduler") or {}):
        out.scheduler.T_0 = a.epochs  # one cosine over the adaptation
    monitor = "val/mae_mm" if a.supervised else "val/loss"
    out.callbacks.checkpoint.monitor = monitor
    out.callbacks.early_stop = {
        "_target_": "lightning.pytorch.callbacks.EarlyStopping",
        "monitor": monitor,
        "mode": "min",
        "patience": a.patience,
    }
    out.optimized_metric = monitor
    # adaptation's own settings are in out.adaptation already, their autos resolved
    own = [o for o in overrides if not o.lstrip("+~").startswith("adaptation.")]
    _override(out, cfg, own, _ADAPT_OWN, f"the run in {run}", "adapt")
    return out


_MISSING = object()
#: classes a run's saved config may name at the module they lived in before odmv/training/
_MOVED = {"odmv.csv_logger.": "odmv.training.csv_logger.", "odmv.sweep.": "odmv.training.sweep."}


def _moved_targets(cfg: DictConfig) -> DictConfig:
    """A saved config with each ``_target_`` at its class's current module (older runs resume)."""

    def walk(x):
        if isinstance(x, dict):
            t = x.get("_target_")
            for old, new in _MOVED.items():
                if isinstance(t, str) and t.startswith(old):
                    x["_target_"] = new + t[len(old) :]
            return {k: walk(v) for k, v in x.items()}
        return [walk(v) for v in x] if isinstance(x, list) else x

    return OmegaConf.create(walk(OmegaConf.to_container(cfg, resolve=False)))


def cfg_value(cfg: DictConfig, key: str, text: str):
    """An override's value as Hydra parsed it into ``cfg`` (``text`` if Hydra dropped it)."""
    value = OmegaConf.select(cfg, key, default=text)
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value


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
        dm.prepare_data()
        dm.setup("fit")
        module.norm = dm.norm  # as the trainer's setup will set it
        target = target_for(module.adapt.target, dm.manifest.images)
        module.adapt = replace(module.adapt, target=target)
        calibration = {"target": module.adapt.target}
        if module.adapt.target == "fringes" and module.adapt.harmonics == "auto":
            # resumed runs choose again
            calibration |= _chosen_fit(cfg, dm, module)
        classical_offsets = None
        if module.adapt.target == "classical":  # resumed runs decode again
            covered, classical_offsets = _classical_targets(dm, module)
            calibration |= covered
        if ckpt is None:  # checked once, on the starting net; a resumed run reads it back
            check = _checked_calibration(cfg, dm, module, classical_offsets)
            write_json(out_dir / CALIBRATION_CHECK, check)
        else:
            check = _recorded_check(out_dir)
        calibration |= check
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


def _chosen_fit(cfg: DictConfig, dm, module: FPPModule) -> dict:
    """``adaptation.harmonics=auto``: the fit chosen by the second harmonic of the held-out
    scenes' fringes under the starting net's depth (the same net on a resumed run), set on
    ``module``; returns the share and the fit for the run's record. The torch random state is
    left as it was, so the run trains as one that named the fit."""
    with torch.random.fork_rng(devices=[]):
        start = load_module(cfg.init_from)
        start.norm = dm.norm  # the run reads images as its start did
        share = second_harmonic_share(start, dm.val_dataloader(), module.adapt)
    module.adapt = chosen_fit(module.adapt, share)
    a = module.adapt
    rank_zero_print(
        f"fringe fit: second harmonic {share:.3f} of the fundamental "
        f"({'>=' if a.harmonics == 2 else '<'} {SECOND_HARMONIC_SHARE}): {a.harmonics} "
        f"harmonic{'s' if a.harmonics > 1 else ''} in {a.window_px} px windows"
    )
    return {"second_harmonic_share": round(share, 4), "fit": f"{a.window_px}:{a.harmonics}"}


def _classical_targets(dm, module: FPPModule) -> tuple[dict, dict[str, float]]:
    """``adaptation.target=classical``: every scene of the user's dataset reconstructed by
    phase shifting from its full sequences, at the net's size, set on ``module`` as its
    targets; returns the share of pixels reconstructed for the run's record and each of the
    dataset's projectors' mean deviation from the others (mm; the calibration check's)."""
    t0 = time.perf_counter()
    ids = [sid for split in dm.splits.values() for sid in split]
    size = (dm.spec.height_px, dm.spec.width_px)
    depths, offsets = classical_depths(dm.manifest, ids, size)
    module.classical_mm = {sid: torch.from_numpy(d.astype(np.float32)) for sid, d in depths.items()}
    covered = float(np.mean([np.isfinite(d).mean() for d in depths.values()]))
    rank_zero_print(
        f"classical target: {len(ids)} scenes reconstructed by phase shifting in "
        f"{time.perf_counter() - t0:.0f} s, {100 * covered:.0f} % of their pixels"
    )
    return {"classical_covered": round(covered, 4)}, offsets


def _recorded_check(out_dir: Path) -> dict:
    """The calibration check a fine-tune made on its starting net, as its first start wrote it
    (a run begun before the check was kept has none)."""
    path = out_dir / CALIBRATION_CHECK
    return json.loads(path.read_text()) if path.is_file() else {}


def _checked_calibration(
    cfg: DictConfig, dm, module: FPPModule, classical_offsets: dict[str, float] | None
) -> dict:
    """Before adapting: where the target is classical, each of the dataset's projectors' own
    depth against the others' (``classical_offsets``: every projector the user captured,
    whatever views the net reads); else each view's mean asked-for depth change of the
    starting net on the held-out scenes. Refused (StaleCalibrationError) where the views
    disagree by more than ``adaptation.stale_mm``; returns them for the run's record."""
    if classical_offsets is not None:
        source, offsets = "classical", classical_offsets
    else:
        source = "net"
        views = list(dm.spec.views)
        offsets = view_offsets(module, dm.val_dataloader(), views, cfg.adaptation.window_px)
    spread = None
    if cfg.adaptation.check_calibration:
        spread = check_calibration(offsets, cfg.adaptation.stale_mm, dm.root, source)
    shown = ", ".join(f"{v} {x:+.3f}" for v, x in offsets.items())
    if len(offsets) < 2:
        rank_zero_print(
            f"calibration check: not possible with one view ({shown} mm): a projector "
            "moved since calibrating would go unseen"
            + (
                ""
                if source == "classical"
                else "; a dataset with the full sequences checks every projector"
            )
        )
    else:
        rank_zero_print(
            f"calibration check ({CHECK_SOURCES[source]}): {shown} mm"
            + ("" if spread is None else f" (spread {spread:.3f} mm <= {cfg.adaptation.stale_mm})")
        )
    return {"calibration_check": source, "view_offsets_mm": offsets, "view_spread_mm": spread}


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


@app("train")
def main(cfg: DictConfig) -> Metrics | JobFailed:
    from hydra.core.hydra_config import HydraConfig

    hydra_dir = Path(HydraConfig.get().runtime.output_dir)
    folders = [hydra_dir]  # removed if the run fails and leaves them empty

    def body() -> tuple[DictConfig, dict]:
        check_launch(cfg)
        if cfg.get("resume"):
            run_cfg = resumed_config(cfg, task_overrides())
        elif cfg.get("adapt"):
            run_cfg = adapted_config(cfg, task_overrides())
        else:
            run_cfg = cfg
        folders.append(Path(run_cfg.paths.output_dir))
        check_continued_folder(run_cfg, task_overrides())
        check_not_held(folders[-1])  # before anything is moved into another run's folder
        adopt_hydra_files(hydra_dir, folders[-1])
        return run_cfg, train(run_cfg)

    result = run_app(body, folders)
    if isinstance(result, JobFailed):
        return result
    run_cfg, metrics = result
    out = Path(run_cfg.paths.output_dir)
    if out.resolve() != hydra_dir.resolve():  # paths.output_dir=DIR, or another run continued
        remove_if_empty(hydra_dir)
    rank_zero_print(f"run folder: {out}")
    if "tensorboard" in (run_cfg.get("logger") or {}):
        rank_zero_print(f"  TensorBoard: {tool('tensorboard')} --logdir {out / 'tensorboard'}")
    if metrics and metrics.get("adapted_from") and "test/mae_mm" not in metrics:
        said = [f"{what} {value}" for what, value in adaptation_lines(metrics)]
        rank_zero_print("  test (no ground truth): " + "; ".join(said))
    elif metrics and "test/mae_mm" in metrics:
        rank_zero_print(f"  test: {test_line(metrics)}; every figure in {out / METRICS}")
        rank_zero_print(f"  its page: {tool('python')} -m odmv.view {out}")
    return Metrics(metrics, run_cfg.get("optimized_metric"))


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


if __name__ == "__main__":
    main()
