"""The report's figures: a bar chart per table, and Fig. 6 (inputs, ground truth, every Table II
model's prediction and |error| on one mm scale for the same test scenes) and Fig. 7 (scanline
profiles) from the runs' kept predictions."""

from __future__ import annotations

import csv
from pathlib import Path

import matplotlib
import numpy as np

from odmv.io.runfolder import PREDICTIONS, SCENES_CSV, recorded_dataset
from odmv.study.results import Cell, Run
from odmv.study.scenes import scene_inputs
from odmv.study.tables import TITLES

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

FIGURE_SCENES = 3  # test scenes in Fig. 6 and 7: one per scene family
TALL_MM = 8.0  # Fig. 6 states each model's error above this height (the metrics' top band)


def bar_chart(path: Path, name: str, cells: list[Cell]) -> None:
    labels = [c.label for c in cells]
    x = np.arange(len(cells))
    fig, ax = plt.subplots(figsize=(max(6, 1.3 * len(cells)), 4))
    for k, (sub, colour, text) in enumerate(
        (("", "tab:blue", "all pixels"), ("_shadowed", "tab:orange", "shadowed pixels"))
    ):
        stats = [c.stat(f"test/mae_mm{sub}") for c in cells]
        means = [s[0] if np.isfinite(s[0]) else 0 for s in stats]
        errs = [s[1] if np.isfinite(s[1]) else 0 for s in stats]
        ax.bar(x + (k - 0.5) * 0.38, means, 0.38, yerr=errs, color=colour, label=text, capsize=3)
    for i, c in enumerate(cells):
        if not c.runs:
            ax.text(i, 0, "missing", ha="center", va="bottom", rotation=90, fontsize=8)
    ax.set_xticks(x, labels, rotation=25, ha="right", fontsize=8)
    ax.set_ylabel("test MAE (mm), mean ± std over seeds")
    ax.set_title(TITLES[name], fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def kept_predictions(run: Run) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    """A run's kept test predictions: scene -> (predicted, true) depth in mm; None without
    its file or without ground truth."""
    path = run.folder / PREDICTIONS
    if not path.is_file():
        return None
    with np.load(path) as z:
        if "depth_mm" not in z:  # an adapted net's, on scenes without ground truth
            return None
        return {
            str(sid): (p, g)
            for sid, p, g in zip(z["scene_id"], z["pred_mm"], z["depth_mm"], strict=True)
        }


def _fringes(dataset: str, sid: str, shape: tuple[int, int]) -> tuple[list[str], list] | None:
    """Every view's input fringe of one scene, from the dataset (None if it is not there)."""
    found = scene_inputs(Path(dataset), sid, shape)
    return (found.views, list(found.fringes.values())) if found else None


def pick_scenes(run: Run, count: int) -> list[str]:
    """Test scenes for the figures: one per family (the one with the most shadowed pixels)."""
    path = run.folder / SCENES_CSV
    if not path.is_file():
        return []
    rows = list(csv.DictReader(path.open()))
    best: dict[str, tuple[float, str]] = {}
    for r in rows:
        share = float(r.get("pixels_shadowed") or 0)
        if share >= best.get(r["family"], (-1.0, ""))[0]:
            best[r["family"]] = (share, r["scene"])
    return [sid for _, sid in sorted(best.values(), reverse=True)][:count]


def comparison_figures(
    out: Path, cells: list[Cell], count: int, error_scale_mm: float
) -> list[str]:
    """Fig. 6 and Fig. 7 for the Table II models (of each row the lowest seed whose predictions
    are on disk; the scenes are picked from an ODMV-Net run's per-scene file where there is one,
    and every run of one test split picks the same ones)."""
    preds = []
    for c in cells:
        runs = c.by_seed()
        p = next((p for p in map(kept_predictions, runs) if p), None)
        if p:
            preds.append((c.label, p))
    if not preds:
        return []
    listed = [r for c in cells for r in c.runs if (r.folder / SCENES_CSV).is_file()]
    if not listed:
        return []
    ref_run = next((r for r in listed if r.model == "odmvnet"), listed[0])
    written = []
    for sid in pick_scenes(ref_run, count):
        if not all(sid in p for _, p in preds):
            continue
        gt = preds[0][1][sid][1]
        lo, hi = float(np.nanmin(gt)), float(np.nanmax(gt))
        n = len(preds)
        recorded = ref_run.metrics.get("dataset")
        dataset = recorded_dataset(ref_run.metrics, ref_run.folder) if recorded else None
        inputs = _fringes(str(dataset), sid, gt.shape) if dataset else None
        cols = max(n, 5)
        # constrained layout: the colour bars take a column of their own, so every panel is
        # the same size
        fig, axes = plt.subplots(
            3, cols, figsize=(2.6 * cols + 1, 8.4), squeeze=False, layout="constrained"
        )
        for ax in axes.flat:
            ax.set_xticks([])
            ax.set_yticks([])
        if inputs:
            for k, (v, img) in enumerate(zip(*inputs, strict=True)):
                axes[0, k].imshow(img, cmap="gray")
                axes[0, k].set_title(f"input {k + 1}: {v}", fontsize=8)
        im = axes[0, 4].imshow(gt, cmap="viridis_r", vmin=lo, vmax=hi)
        axes[0, 4].set_title("ground truth (mm)", fontsize=8)
        fig.colorbar(im, ax=axes[:2, :].ravel().tolist(), fraction=0.02, label="depth (mm)")
        tall = hi - gt >= TALL_MM  # height above the base plane, the farthest depth
        for k, (label, p) in enumerate(preds):
            pred = p[sid][0]
            axes[1, k].imshow(pred, cmap="viridis_r", vmin=lo, vmax=hi)
            axes[1, k].set_title(label, fontsize=7, wrap=True)
            err = np.abs(pred - gt)
            im = axes[2, k].imshow(err, cmap="inferno", vmin=0, vmax=error_scale_mm)
            above = f"\nabove {TALL_MM:g} mm: {np.nanmean(err[tall]):.2f} mm" if tall.any() else ""
            axes[2, k].set_title(f"|error|, MAE {np.nanmean(err):.3f} mm{above}", fontsize=7)
        fig.colorbar(im, ax=axes[2, :].tolist(), fraction=0.02, label="|error| (mm)",
                     extend="max")  # fmt: skip
        unused = list(axes[0, len(inputs[0]) if inputs else 0 : 4]) + list(axes[0, 5:])
        for ax in unused + list(axes[1:, n:].flat):
            ax.axis("off")
        fig.suptitle(
            f"Fig. 6 layout: test scene {sid} (|error| on a 0-{error_scale_mm} mm scale; "
            f"each panel's MAE on parts above {TALL_MM:g} mm, where the scale saturates)"
        )
        name = f"fig6_scene{sid}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        written.append(name)
        # Fig. 7: the row through the most shadowed region is where models differ
        row = gt.shape[0] // 2
        fig, ax = plt.subplots(figsize=(8, 4))
        x = np.arange(gt.shape[1])
        ax.plot(x, gt[row], "k-", lw=2, label="ground truth")
        for label, p in preds:
            ax.plot(x, p[sid][0][row], lw=1, label=label)
        ax.invert_yaxis()
        ax.set_xlabel("column (px)")
        ax.set_ylabel("depth (mm)")
        ax.set_title(f"Fig. 7 layout: profile of scene {sid}, row {row}")
        ax.legend(fontsize=7)
        fig.tight_layout()
        name = f"fig7_scene{sid}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        written.append(name)
    return written
