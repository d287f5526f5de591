"""A finished run's best checkpoint on its training or validation split: does the net fit
what it trained on? (Underfitting and overfitting look alike in the test error alone.)

    python -m odmv.study split outputs/accuracy/s4-w16-l1-seed0 --split train
    python -m odmv.study heights --file train_predictions.npz --tall 12 'S4=...-seed*'

Writes ``<split>_predictions.npz`` into each run folder (scene_id, pred_mm, depth_mm: the
arrays of the run's test_predictions.npz), atomically, and prints the split's MAE in mm. The
run's own data settings are used (no augmentation), read from its checkpoint; the dataset must
exist (it is never rendered here).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from odmv.io.atomic import write_npz
from odmv.study.records import run_data


def split_predictions(run: Path, split: str) -> tuple[Path, float]:
    """Predict ``split`` with ``run``'s best checkpoint; returns the file written and the MAE."""
    module, dm = run_data(run, "fit")
    ids, preds, depths = [], [], []
    with torch.no_grad():
        for batch in dm._loader(split, shuffle=False):
            preds.append(module.depth_mm(module.run(batch))[:, 0].numpy())
            depths.append(batch["depth_mm"][:, 0].numpy())
            ids.extend(batch["scene_id"])
    pred, depth = np.concatenate(preds), np.concatenate(depths)
    out = run / f"{split}_predictions.npz"
    arrays = {"scene_id": np.array(ids), "pred_mm": pred, "depth_mm": depth}
    write_npz(out, arrays)
    valid = np.isfinite(depth)
    return out, float(np.abs(pred - depth)[valid].mean())


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="finished run folders")
    ap.add_argument("--split", default="train", choices=("train", "val"))
    args = ap.parse_args(argv)
    for run in args.runs:
        out, mae = split_predictions(run, args.split)
        print(f"{run}: {args.split} MAE {mae:.4f} mm -> {out}")
