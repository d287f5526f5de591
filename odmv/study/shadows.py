"""Test MAE on the shadowed pixels, split by what the first view sees there and by height.

    python -m odmv.study shadows 'S4=outputs/accuracy/s4-w16-l1-seed*' ...

A shadowed pixel (odmv.data.subsets) lies in some projector's footprint but is unlit by one
that covers it. For a net that sees only the first view (right), the pixels that view does
not light carry no fringe at all; those it lights do. If a net's error on shadowed pixels
comes from the missing fringe, it is larger on the first kind; if it comes from where shadows
lie (beside the parts' edges), it is alike on both. Each argument is ``LABEL=GLOB`` (finished
run folders with test_predictions.npz); the masks come from each run's dataset (it must
exist). Heights as in height_errors.py. Prints a markdown table, means over each label's runs.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from odmv.io.runfolder import METRICS, PREDICTIONS
from odmv.study.heights import BANDS_MM
from odmv.study.records import load_predictions, run_data, run_groups


def test_masks(run: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per test scene: (shadowed, lit in the first view) as boolean H x W maps."""
    _, dm = run_data(run, "test", views=["right", "down", "left", "up"])
    out = {}
    for sample in dm.datasets["test"]:
        shadowed = sample["shadowed"][0].numpy() > 0.5
        out[sample["scene_id"]] = (shadowed, sample["lit"][0].numpy() > 0.5)
    return out


def shadow_row(run: Path, masks: dict) -> list[float]:
    """MAE (mm) on shadowed pixels per height band, then where the first view lights them,
    where it does not, and on all shadowed pixels."""
    ids, pred, depth = load_predictions(run, PREDICTIONS)
    shadowed = np.stack([masks[str(s)][0] for s in ids]) & np.isfinite(depth)
    lit = np.stack([masks[str(s)][1] for s in ids])
    err, height = np.abs(pred - depth), np.nanmax(depth) - depth

    def mae(m):
        return float(err[m].mean()) if m.any() else np.nan

    bands = zip(BANDS_MM[:-1], BANDS_MM[1:], strict=True)
    row = [mae(shadowed & (height >= lo) & (height < hi)) for lo, hi in bands]
    return row + [mae(shadowed & lit), mae(shadowed & ~lit), mae(shadowed)]


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("groups", nargs="+", metavar="LABEL=GLOB")
    args = ap.parse_args(argv)
    groups = [run_groups(group, PREDICTIONS) for group in args.groups]  # each found, or refused
    bands = [
        f"{lo:g}-{hi:g} mm" if np.isfinite(hi) else f"> {lo:g} mm"
        for lo, hi in zip(BANDS_MM[:-1], BANDS_MM[1:], strict=True)
    ]
    cols = bands + ["lit in view 1", "unlit in view 1", "all shadowed"]
    print("| MAE (mm) on shadowed pixels | runs | " + " | ".join(cols) + " |")
    print("|---|---:|" + "---:|" * len(cols))
    masks: dict[str, dict] = {}  # per dataset: one test split's masks
    for label, folders in groups:
        rows = []
        for f in folders:
            dataset = json.loads((f / METRICS).read_text())["dataset"]
            if dataset not in masks:
                masks[dataset] = test_masks(f)
            rows.append(shadow_row(f, masks[dataset]))
        rows = np.array(rows)
        cells = [f"{np.nanmean(c):.3f}" if np.isfinite(c).any() else "–" for c in rows.T]
        print(f"| {label} | {len(folders)} | " + " | ".join(cells) + " |")
