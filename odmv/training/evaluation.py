"""A checkpoint evaluated on a test split: mm metrics beside a constant-depth predictor, per
scene family, and figures (``python -m odmv.evaluate`` runs it; what it writes: that app's
docstring)."""

from __future__ import annotations

import csv
from pathlib import Path

import hydra
import lightning as L
import matplotlib
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from odmv.cli import set_threads, task_overrides
from odmv.data.dataset import DataError
from odmv.data.views import MissingViews
from odmv.io.atomic import write_json
from odmv.io.manifest import MANIFEST
from odmv.io.runfolder import METRICS, PREDICTIONS, SCENES_CSV
from odmv.training.metrics import DepthErrors
from odmv.training.module import batched, load_module

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def read_only(data: dict, **changes) -> dict:
    """A saved data config (a checkpoint's) that reads its dataset with its ground truth (an
    adapted net's was read without) and never renders one, with ``changes`` on top."""
    quiet = {"progress": False, "render": False, "simulate": None, "labels": True}
    quiet["val_from_train"] = None  # a split of the training scenes is no test's business
    return {**data, **quiet, **changes}


def checkpoint_datamodule(module, stage: str | None, **changes):
    """The data module that reads a trained module's dataset as it was trained (:func:`read_only`,
    ``changes`` on top), set up for ``stage`` (None: every split)."""
    data = read_only(module.hparams.data_cfg, **{"views": list(module.hparams.views), **changes})
    dm = hydra.utils.instantiate(data, _convert_="all")
    dm.prepare_data()
    dm.setup(stage)
    return dm


def constant_predictor_errors(dm, value_mm: float) -> dict[str, float]:
    """Errors of predicting one depth everywhere (the mean training depth)."""
    metric = DepthErrors()
    for batch in dm.test_dataloader():
        metric.update(
            torch.full_like(batch["depth_mm"], value_mm), batch["depth_mm"], batch["valid"]
        )
    return {k: float(v) for k, v in metric.compute().items() if k != "pixels"}


def constant_depth_mm(saved: dict, dm) -> float | None:
    """The constant predictor's depth (mm): the mean training depth of the dataset the net was
    trained on (the checkpoint's), so a test on another dataset is scored against the same
    constant; else (or for an adapted net, whose dataset has no depth) the tested dataset's
    own training split; None where neither is at hand."""
    root = saved.get("root") if saved.get("labels", True) else None
    if (
        root
        and Path(root).resolve() != Path(dm.root).resolve()
        and (Path(root) / MANIFEST).is_file()
    ):
        own = hydra.utils.instantiate(read_only(saved), _convert_="all")
        const = own.mean_depth_mm("train")
        if const is not None:
            return const
    return dm.mean_depth_mm("train")


def family_errors(out_dir: Path, const_mm: float | None) -> dict[str, float]:
    """MAE in mm per scene family over the test pixels, of the model
    (``family/<family>/mae_mm``) and of the constant predictor
    (``family/<family>/constant_mae_mm``, unless ``const_mm`` is None), from the per-scene
    outputs the test wrote."""
    with (out_dir / SCENES_CSV).open() as fh:
        family = {r["scene"]: r["family"] or "unlabelled" for r in csv.DictReader(fh)}
    pred = np.load(out_dir / PREDICTIONS)
    out = {}
    for fam in sorted(set(family.values())):
        pick = np.array([family[str(s)] == fam for s in pred["scene_id"]])
        gt, p = pred["depth_mm"][pick].astype(np.float64), pred["pred_mm"][pick]
        valid = np.isfinite(gt)
        out[f"family/{fam}/mae_mm"] = float(np.abs(p[valid] - gt[valid]).mean())
        if const_mm is not None:
            out[f"family/{fam}/constant_mae_mm"] = float(np.abs(const_mm - gt[valid]).mean())
    return out


def save_figure(
    path: Path,
    sample: dict,
    pred_mm: np.ndarray,
    views: list[str],
    error_scale_mm: float,
    row: int | None,
) -> None:
    """Inputs, GT, prediction, |error| and a scanline profile for one sample."""
    gt = sample["depth_mm"][0].numpy()
    fringes = sample["fringes"].numpy()
    lit = sample["lit"].numpy()
    row = gt.shape[0] // 2 if row is None else row
    s = len(views)
    fig, axes = plt.subplots(2, max(s, 4), figsize=(3.2 * max(s, 4), 6.4), squeeze=False)
    for k, v in enumerate(views):
        axes[0, k].imshow(fringes[k], cmap="gray", vmin=-1, vmax=1)
        axes[0, k].set_title(f"input {k + 1}: {v}")
    lo, hi = float(np.nanmin(gt)), float(np.nanmax(gt))
    im = axes[1, 0].imshow(gt, cmap="viridis_r", vmin=lo, vmax=hi)
    axes[1, 0].set_title("ground truth depth (mm)")
    fig.colorbar(im, ax=axes[1, 0], fraction=0.046)
    im = axes[1, 1].imshow(pred_mm, cmap="viridis_r", vmin=lo, vmax=hi)
    axes[1, 1].set_title("prediction (mm)")
    fig.colorbar(im, ax=axes[1, 1], fraction=0.046)
    err = np.abs(pred_mm - gt)
    im = axes[1, 2].imshow(err, cmap="inferno", vmin=0, vmax=error_scale_mm)
    axes[1, 2].set_title(f"|error| (mm), MAE {np.nanmean(err):.3f}")
    fig.colorbar(im, ax=axes[1, 2], fraction=0.046)
    for ax in (axes[1, 0], axes[1, 1], axes[1, 2]):
        ax.axhline(row, color="red", lw=0.8)
    x = np.arange(gt.shape[1])
    ax = axes[1, 3]
    ax.plot(x, gt[row], "k-", lw=1.2, label="ground truth")
    ax.plot(x, pred_mm[row], "r-", lw=1.0, label="prediction")
    shadow = (lit[:, row] < 0.5).any(0)
    ax.fill_between(x, lo, hi, where=shadow, color="0.85", label="shadowed in a view")
    ax.invert_yaxis()
    ax.set_title(f"profile, row {row}")
    ax.set_xlabel("column (px)")
    ax.set_ylabel("depth (mm)")
    ax.legend(fontsize=7)
    for ax in axes.flat:
        if ax is not axes[1, 3]:
            ax.set_xticks([])
            ax.set_yticks([])
    for ax in axes[0, s:]:
        ax.axis("off")
    fig.suptitle(f"scene {sample['scene_id']}")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def data_settings(saved: dict, cfg: DictConfig, overrides: list[str]) -> dict:
    """The checkpoint's data settings, changed only where the command line says so:
    ``root=PATH`` (or ``data.root=PATH``) points them at another dataset and ``data.KEY=VALUE``
    changes one setting. The dataset is read, never rendered: a missing one is an error."""
    data = dict(saved)
    for override in overrides:
        key = override.partition("=")[0].lstrip("+~")
        if key == "root":
            data["root"] = cfg.root
        elif key.startswith("data."):
            name = key.split(".")[1]
            value = OmegaConf.select(cfg, f"data.{name}")
            data[name] = (
                OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
            )
    if data.get("root") is None:
        raise ValueError("root: the checkpoint names no dataset; give root=PATH")
    data["root"] = str(Path(data["root"]).resolve())
    if not (Path(data["root"]) / MANIFEST).is_file():
        raise DataError(
            f"{data['root']}: no dataset here (root=PATH names the dataset to test on; "
            "evaluation never renders one)"
        )
    return read_only(data)


def mark_missing(dm, module, missing: list[str], ckpt_path) -> list[str]:
    """Make ``missing`` views missing in every test sample (a net trained with view dropout
    only: any other would read them as dark images); returns the views used."""
    views = list(module.hparams.views)
    if not missing:
        return views
    unknown = [v for v in missing if v not in views]
    if unknown or len(missing) >= len(views):
        raise ValueError(f"missing={missing}: name some, not all, of the net's views {views}")
    if not (module.hparams.input_spec or {}).get("availability"):
        raise ValueError(
            f"missing={missing}: {ckpt_path} was not trained with view_dropout, so it cannot be "
            "told that a view is missing (it would read a dark image)"
        )
    keep = torch.tensor([v not in missing for v in views])
    dm.datasets["test"] = MissingViews(dm.datasets["test"], keep)
    return [v for v in views if v not in missing]


def evaluate(cfg: DictConfig, overrides: list[str] | None = None) -> dict:
    """Test metrics and figures for ``cfg.ckpt_path``; returns the metrics dict.
    ``overrides``: the command line's (default: Hydra's), which pick the data settings
    that differ from the checkpoint's (:func:`data_settings`)."""
    set_threads(cfg.get("threads"))
    out_dir = Path(cfg.paths.output_dir)
    module = load_module(cfg.ckpt_path)
    overrides = task_overrides() if overrides is None else overrides
    data_cfg = data_settings(dict(module.hparams.data_cfg or {}), cfg, overrides)
    data_cfg["views"] = list(module.hparams.views)  # the views the net was trained on
    dm = hydra.utils.instantiate(data_cfg, _convert_="all")
    dm.prepare_data()
    dm.setup("test")  # the test split only; the constant needs just the training depth maps
    used = mark_missing(dm, module, list(cfg.get("missing") or []), cfg.ckpt_path)
    print(
        f"evaluating {cfg.ckpt_path} on the test split of {dm.root} (views: {', '.join(used)})",
        flush=True,
    )
    trainer = L.Trainer(
        accelerator=cfg.accelerator,
        devices=1,
        logger=False,
        enable_progress_bar=cfg.progress,
        enable_model_summary=False,
    )
    module.test_dir = out_dir
    results = trainer.test(module, datamodule=dm, verbose=False)[0]
    metrics = {k: float(v) for k, v in results.items()}
    const = constant_depth_mm(dict(module.hparams.data_cfg or {}), dm)
    if const is not None:
        errors = constant_predictor_errors(dm, const)
        metrics.update({f"constant/{k}": v for k, v in errors.items()})
        metrics["constant/depth_mm"] = const
    metrics.update(family_errors(out_dir, const))
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / METRICS, metrics)
    module.eval()
    ds = dm.datasets["test"]
    with torch.no_grad():
        for i in range(min(cfg.figures, len(ds))):
            sample = ds[i]
            out = module.run(batched(sample))
            pred_mm = module.depth_mm(out)[0, 0].numpy()
            save_figure(
                out_dir / "figures" / f"{sample['scene_id']}.png",
                sample,
                pred_mm,
                list(dm.spec.views),
                cfg.error_scale_mm,
                cfg.scanline,
            )
    return metrics


def edges_line(metrics: dict, stage: str = "test") -> str:
    """The MAE on interior and edge pixels with their shares, and a phase head's wrong fringe
    orders: one line (empty for a record that predates them)."""
    if f"{stage}/mae_mm_interior" not in metrics:
        return ""
    line = (
        f"interior  : MAE {metrics[f'{stage}/mae_mm_interior']:.4f} mm on "
        f"{metrics[f'{stage}/share_interior']:.1%} of the pixels; edge band (within 1 px of a "
        f"depth jump > 1 mm): MAE {metrics[f'{stage}/mae_mm_edge']:.4f} mm on "
        f"{metrics[f'{stage}/share_edge']:.1%}"
    )
    if f"{stage}/order_wrong" in metrics:
        line += f"; wrong fringe orders {metrics[f'{stage}/order_wrong']:.2%} of lit view pixels"
    return line + "\n"


def report(metrics: dict) -> str:
    """The model and the constant-depth predictor in mm, overall and per scene family."""
    families = [
        k.split("/")[1] for k in metrics if k.startswith("family/") and k.endswith("/mae_mm")
    ]
    lines = []
    for fam in families:
        model = metrics[f"family/{fam}/mae_mm"]
        const = metrics.get(f"family/{fam}/constant_mae_mm")
        vs = "" if const is None else f", constant {const:.4f} mm ({const / model:.1f}x)"
        lines.append(f"  {fam:<10}: MAE {model:.4f} mm{vs}")
    tail = "\n".join(["per scene family:", *lines]) if lines else ""
    constant = (
        f"constant  : MAE {metrics['constant/mae_mm']:.4f} mm, "
        f"RMSE {metrics['constant/rmse_mm']:.4f} mm (predicting "
        f"{metrics['constant/depth_mm']:.3f} mm everywhere)"
        if "constant/depth_mm" in metrics
        else "constant  : none (no training scenes here, nor the checkpoint's dataset on disk)"
    )
    return (
        f"model     : MAE {metrics['test/mae_mm']:.4f} mm, RMSE {metrics['test/rmse_mm']:.4f} mm"
        f" (shadowed pixels: MAE {metrics['test/mae_mm_shadowed']:.4f} mm)\n"
        + edges_line(metrics)
        + constant
        + ("\n" + tail if tail else "")
    )
