"""A finished run's best checkpoint on its training or validation split: does the net fit
what it trained on? (Underfitting and overfitting look alike in the test error alone.)

    python experiments/split_predictions.py outputs/accuracy/s4-w16-l1-seed0 --split train
    python experiments/height_errors.py --file train_predictions.npz --tall 12 'S4=...-seed*'

Writes ``<split>_predictions.npz`` into each run folder (scene_id, pred_mm, depth_mm: the
arrays of the run's test_predictions.npz), atomically, and prints the split's MAE in mm. The
run's own data settings are used (no augmentation), read from its checkpoint; the dataset must
exist (it is never rendered here).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import hydra
import numpy as np
import torch

import odmv.config  # noqa: F401  (registers the config resolvers)
from odmv.evaluate import read_only
from odmv.heldout import best_checkpoint
from odmv.module import load_module, net_input


def run_data(run: Path, stage: str, views: list[str] | None = None):
    """A finished run's best checkpoint (eval mode) and its data module set up for ``stage``,
    with the run's data settings (``views``: other views than the run's)."""
    module = load_module(best_checkpoint(run)[0]).eval()
    views = list(module.hparams.views) if views is None else views
    data = read_only(module.hparams.data_cfg, views=views)
    dm = hydra.utils.instantiate(data, _convert_="all")
    dm.prepare_data()
    dm.setup(stage)
    return module, dm


def split_predictions(run: Path, split: str) -> tuple[Path, float]:
    """Predict ``split`` with ``run``'s best checkpoint; returns the file written and the MAE."""
    module, dm = run_data(run, "fit")
    ids, preds, depths = [], [], []
    with torch.no_grad():
        for batch in dm._loader(split, shuffle=False):
            preds.append(module.depth_mm(module(net_input(batch)))[:, 0].numpy())
            depths.append(batch["depth_mm"][:, 0].numpy())
            ids.extend(batch["scene_id"])
    pred, depth = np.concatenate(preds), np.concatenate(depths)
    out = run / f"{split}_predictions.npz"
    tmp = run / f".{out.name}.{os.getpid()}.tmp.npz"
    np.savez_compressed(tmp, scene_id=np.array(ids), pred_mm=pred, depth_mm=depth)
    os.replace(tmp, out)
    valid = np.isfinite(depth)
    return out, float(np.abs(pred - depth)[valid].mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="finished run folders")
    ap.add_argument("--split", default="train", choices=("train", "val"))
    args = ap.parse_args()
    for run in args.runs:
        out, mae = split_predictions(run, args.split)
        print(f"{run}: {args.split} MAE {mae:.4f} mm -> {out}")


if __name__ == "__main__":
    main()
