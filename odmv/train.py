"""Train a net: ``python -m odmv.train model=odmvnet views=4`` (config: conf/train.yaml).

A thin Hydra wrapper around :func:`train`, which tests call with a composed config. After
fitting it tests the best checkpoint and writes ``metrics.json`` and ``metrics.csv`` (one row
with the run's overrides) into the run folder; multiruns also collect every job into
``results.csv`` in the sweep folder (odmv.sweep).
"""

from __future__ import annotations

import time
from pathlib import Path

import hydra
import lightning as L
from omegaconf import DictConfig, OmegaConf

import odmv.config  # noqa: F401  (registers the config resolvers)
from odmv.cli import run_app
from odmv.module import FPPModule, write_json
from odmv.simulate import CONF_DIR
from odmv.sweep import append_row


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "/"))
        else:
            out[key] = v if isinstance(v, (int, float, str, bool)) or v is None else str(v)
    return out


def build(cfg: DictConfig):
    """Data module, module, trainer from a composed config (shared with evaluation)."""
    dm = hydra.utils.instantiate(cfg.data, _convert_="all")
    module = FPPModule(
        net_cfg=OmegaConf.to_container(cfg.model.net, resolve=True),
        loss=OmegaConf.to_container(cfg.loss, resolve=True),
        optimizer=OmegaConf.to_container(cfg.optimizer, resolve=True),
        scheduler=OmegaConf.to_container(cfg.scheduler, resolve=True),
        log_images=cfg.log_images,
        data_cfg=OmegaConf.to_container(cfg.data, resolve=True),
    )
    loggers = [hydra.utils.instantiate(c) for c in (cfg.get("logger") or {}).values()]
    callbacks = [hydra.utils.instantiate(c) for c in (cfg.get("callbacks") or {}).values()]
    trainer = hydra.utils.instantiate(cfg.trainer, logger=loggers or False, callbacks=callbacks)
    return dm, module, trainer


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit, then test the best checkpoint; returns the test metrics (mm)."""
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    out_dir = Path(cfg.paths.output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    dm, module, trainer = build(cfg)
    for lg in trainer.loggers:
        lg.log_hyperparams(_flat(OmegaConf.to_container(cfg, resolve=True)))
    t0 = time.perf_counter()
    trainer.fit(module, datamodule=dm, ckpt_path=cfg.ckpt_path)
    train_seconds = time.perf_counter() - t0
    dm.save_split(out_dir / "split.json")
    metrics: dict = {}
    if cfg.test:
        best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
        module.test_dir = out_dir
        results = trainer.test(module, datamodule=dm, ckpt_path=best or None, weights_only=True)
        metrics = {k: float(v) for k, v in results[0].items()}
        overrides = _task_overrides()
        metrics.update(
            best_checkpoint=best,
            train_seconds=round(train_seconds, 1),
            epochs=trainer.current_epoch,
            parameters=sum(p.numel() for p in module.net.parameters()),
            model=cfg.model.name,
            views=list(dm.spec.views),
            ablation=cfg.get("ablation"),
            seed=cfg.seed,
            dataset=str(Path(dm.root).resolve()),
            overrides=" ".join(overrides),
        )
        write_json(out_dir / "metrics.json", metrics)
        append_row(
            out_dir / "metrics.csv",
            {k: v for k, v in metrics.items() if not isinstance(v, list)},
        )
    return metrics


def _task_overrides() -> list[str]:
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="train")
def main(cfg: DictConfig) -> dict[str, float]:
    out = Path(cfg.paths.output_dir)
    metrics = run_app(lambda: train(cfg), out)
    print(f"run folder: {out}\n  TensorBoard: tensorboard --logdir {out / 'tensorboard'}")
    if metrics:
        print(
            "  test: "
            + ", ".join(f"{k}={v:.4f}" for k, v in metrics.items() if k.startswith("test/"))
        )
    return metrics


if __name__ == "__main__":
    main()
