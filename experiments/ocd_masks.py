"""Do ODMV-Net's occlusion detectors find the unlit pixels? Compares each OCD mask with the
simulator's lit masks on a checkpoint's test split.

    python experiments/ocd_masks.py CKPT [CKPT ...]

Prints, per checkpoint and decoder level (0 = full resolution), the mean mask value on pixels a
projector lights and on pixels it does not, and the ROC AUC of the mask as a lit/unlit detector
(0.5: no information; 1: separates them perfectly).
"""

from __future__ import annotations

import sys

import hydra
import numpy as np
import torch

from odmv.losses import resize_target
from odmv.module import load_module, net_input


def auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Mann-Whitney ROC AUC of ``scores`` for binary ``labels``."""
    order = np.argsort(scores, kind="mergesort")
    ranks = np.empty(len(scores))
    ranks[order] = np.arange(1, len(scores) + 1)
    pos = labels.astype(bool)
    n_pos, n_neg = pos.sum(), (~pos).sum()
    if not n_pos or not n_neg:
        return float("nan")
    return float((ranks[pos].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def main(paths: list[str]) -> int:
    if not paths:
        print(__doc__, file=sys.stderr)
        return 2
    for path in paths:
        module = load_module(path).eval()
        cfg = dict(module.hparams.data_cfg, progress=False, views=list(module.hparams.views))
        dm = hydra.utils.instantiate(cfg, _convert_="all")
        dm.prepare_data()
        dm.setup()
        masks: dict[int, list] = {}
        with torch.no_grad():
            for batch in dm.test_dataloader():
                out = module(net_input(batch))
                if "occlusion" not in out:
                    print(f"{path}: this model has no occlusion detector")
                    break
                for level, m in enumerate(out["occlusion"]):
                    lit = resize_target(batch["lit"], m.shape[-2:])
                    masks.setdefault(level, []).append((m[:, 0].numpy(), lit.numpy()))
        print(path)
        for level, pairs in masks.items():
            m = np.concatenate([p[0].ravel() for p in pairs])
            lit = np.concatenate([p[1].ravel() for p in pairs]) > 0.5
            print(
                f"  level {level}: mask on lit {m[lit].mean():.3f}, on unlit "
                f"{m[~lit].mean():.3f}, AUC {auc(m, lit):.3f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
