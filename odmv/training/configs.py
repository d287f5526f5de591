"""A training's config from the command line: the settings a run records and its module
reads (:func:`data_config`, :func:`run_summary`, :func:`adapt_settings`,
:func:`distill_settings`), the whole numbers it refuses by name, and the config of
``resume=RUN`` (the run's own, continued) and of ``adapt=true init_from=RUN root=DATASET``
(RUN's own, pointed at the user's fringes) with the command line's overrides on top."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from odmv.data.dataset import matching_fringe
from odmv.io.manifest import MANIFEST, load_manifest
from odmv.io.runfolder import recorded_dataset
from odmv.rig import whole_number
from odmv.training.checkpoint import checkpoint_path, read_checkpoint
from odmv.training.consistency import resolved_adaptation


def run_config(cfg: DictConfig, overrides: list[str]) -> DictConfig:
    """The config the command line trains: ``resume=RUN``'s, ``adapt=true``'s, or its own."""
    if cfg.get("resume"):
        return resumed_config(cfg, overrides)
    if cfg.get("adapt"):
        return adapted_config(cfg, overrides)
    return cfg


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
