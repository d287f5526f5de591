"""Test MAE by height above the base plane: where in depth the error of finished runs lies.

    python -m odmv.study heights 'UNet=outputs/reproduce/mini/unet-s1-seed*' ...

Each argument is ``LABEL=GLOB`` (run folders holding test_predictions.npz, or --file).
Heights are in mm above the base plane, the largest ground-truth depth of the split (the plane
is the farthest surface the camera sees). Prints a markdown table: the share of valid pixels
in each height band, then per label the scenes each run's file holds (a committed reproduction
record keeps only its figure scenes) and the MAE in each band, mean ± std over the matched runs.

    python -m odmv.study heights --tall 8 'UNet=outputs/reproduce/mini/unet-s1-seed*'

adds, per test scene with pixels higher than 8 mm, how many there are and the mean true and
predicted height there (mean over each label's runs): which parts the tall-band error is.
"""

from __future__ import annotations

import argparse

import numpy as np

from odmv.io.runfolder import PREDICTIONS
from odmv.study.records import load_predictions, run_groups

BANDS_MM = [0.0, 0.5, 2.0, 5.0, 8.0, 12.0, np.inf]


def band_errors(pred: np.ndarray, depth: np.ndarray, bands: list[float]):
    """Per band: MAE (mm) and the share of valid pixels."""
    valid = np.isfinite(depth)
    height = np.nanmax(depth) - depth
    err = np.abs(pred - depth)
    mae, share = [], []
    for lo, hi in zip(bands[:-1], bands[1:], strict=True):
        m = valid & (height >= lo) & (height < hi)
        hit = m & np.isfinite(err)  # a method that leaves pixels out is scored where it answers
        mae.append(err[hit].mean() if hit.any() else np.nan)
        share.append(m.sum() / valid.sum())
    return np.array(mae), np.array(share)


def tall_scenes(ids, pred, depth, above_mm: float) -> dict[str, tuple[int, float, float]]:
    """Per scene with pixels above ``above_mm``: (pixels, mean true height, mean predicted
    height) there, heights in mm above the base plane as in :func:`band_errors`."""
    plane = np.nanmax(depth)
    out = {}
    for sid, p, d in zip(ids, pred, depth, strict=True):
        m = np.isfinite(d) & (plane - d > above_mm) & np.isfinite(p)
        if m.any():
            true_mm, pred_mm = (plane - d[m]).mean(), (plane - p[m]).mean()
            out[str(sid)] = (int(m.sum()), float(true_mm), float(pred_mm))
    return out


def print_tall(groups: list[tuple[str, list]], above_mm: float) -> None:
    """``groups``: (label, the runs' loaded predictions)."""
    per_label = [(label, [tall_scenes(*r, above_mm) for r in runs]) for label, runs in groups]
    scenes = sorted({s for _, runs in per_label for r in runs for s in r})
    print(
        f"\n| scene | pixels > {above_mm:g} mm | true height (mm) | "
        + " | ".join(f"{label}: predicted (mm)" for label, _ in per_label)
        + " |"
    )
    print("|---|---:|---:|" + "---:|" * len(per_label))
    for s in scenes:
        first = next(r[s] for _, runs in per_label for r in runs if s in r)
        cells = []
        for _, runs in per_label:
            seen = [r[s][2] for r in runs if s in r]
            cells.append(f"{np.mean(seen):.1f}" if seen else "–")
        print(f"| {s} | {first[0]} | {first[1]:.1f} | " + " | ".join(cells) + " |")


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("groups", nargs="+", metavar="LABEL=GLOB")
    ap.add_argument("--tall", type=float, metavar="MM", help="per scene: the pixels above MM")
    ap.add_argument(
        "--file",
        default=PREDICTIONS,
        help="predictions file in each run folder (python -m odmv.study split writes "
        "train_predictions.npz and val_predictions.npz)",
    )
    args = ap.parse_args(argv)
    names = [
        f"{lo:g}-{hi:g} mm" if np.isfinite(hi) else f"> {lo:g} mm"
        for lo, hi in zip(BANDS_MM[:-1], BANDS_MM[1:], strict=True)
    ]
    rows, share, groups = [], None, []
    for group in args.groups:
        label, folders = run_groups(group, args.file)
        runs = [load_predictions(f, args.file) for f in folders]
        groups.append((label, runs))
        results = [band_errors(pred, depth, BANDS_MM) for _, pred, depth in runs]
        share = results[0][1]
        mae = np.stack([r[0] for r in results])
        cells = [f"{m:.2f}" for m in mae.mean(axis=0)]
        if len(mae) > 1:  # one run has no spread to print
            std = mae.std(axis=0, ddof=1)
            cells = [f"{c} ± {s:.2f}" for c, s in zip(cells, std, strict=True)]
        # a reproduction record keeps only its figure scenes: say how many each run scored
        scenes = "/".join(sorted({str(len(ids)) for ids, _, _ in runs}))
        rows.append(f"| {label} | {len(folders)} | {scenes} | " + " | ".join(cells) + " |")
    print("| MAE (mm) by height above the plane | runs | scenes | " + " | ".join(names) + " |")
    print("|---|---:|---:|" + "---:|" * len(names))
    cells = " | ".join(f"{s * 100:.1f} %" for s in share)
    print(f"| share of valid pixels | – | – | {cells} |")
    print("\n".join(rows))
    if args.tall is not None:
        print_tall(groups, args.tall)
