"""Do ODMV-Net's occlusion detectors find the unlit pixels, and how does its fusion weigh the
views? Compares each OCD mask and each fusion's blend weights with the simulator's lit masks on
a checkpoint's test split.

    python -m odmv.study ocd CKPT [CKPT ...]

Prints, per checkpoint and decoder level (0 = full resolution), the mean mask value on pixels a
projector lights and on pixels it does not, and the ROC AUC of the mask as a lit/unlit detector
(0.5: no information; 1: separates them perfectly). Then, per fusion (Main, Aux1, Aux2), how
many views the blend uses (exp of the weights' entropy: S for an even blend, 1 for one view),
the largest weight, and on pixels that some views light and others do not, the mean weight of
a lit and of an unlit view and the weights' AUC as a lit/unlit detector.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from odmv.models.blocks import OcclusionAwareFusion
from odmv.study.records import checkpoint_data
from odmv.training.checkpoint import CheckpointError
from odmv.training.losses import resize_target

HEADS = ("Main", "Aux1", "Aux2")


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


def blend_summary(pairs: list) -> str:
    """Blend weights (B x S x h x w) against lit masks of the same shape, as one line."""
    w = (
        np.concatenate([p[0] for p in pairs])
        .transpose(1, 0, 2, 3)
        .reshape(pairs[0][0].shape[1], -1)
    )
    lit = np.concatenate([p[1] for p in pairs]).transpose(1, 0, 2, 3).reshape(w.shape) > 0.5
    entropy = -(w * np.log(np.clip(w, 1e-12, None))).sum(0)
    used, largest = np.exp(entropy).mean(), w.max(0).mean()
    line = f"{used:.2f} of {w.shape[0]} views used, largest weight {largest:.3f}"
    mixed = lit.any(0) & ~lit.all(0)
    if mixed.any():
        wm, lm = w[:, mixed].ravel(), lit[:, mixed].ravel()
        line += (
            f"; where views differ ({mixed.mean():.0%} of pixels): lit view {wm[lm].mean():.3f},"
            f" unlit {wm[~lm].mean():.3f}, AUC {auc(wm, lm):.3f}"
        )
    return line


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoints", nargs="+", metavar="CKPT")
    for path in parser.parse_args(argv).checkpoints:
        try:
            module, dm = checkpoint_data(path, None)
        except CheckpointError as e:
            raise SystemExit(f"error: {e}") from None
        masks: dict[int, list] = {}
        blends: list[torch.Tensor] = []  # each fusion's weights, B x S x h x w, in call order

        def keep_blend(_fusion, _args, out, blends=blends):
            blends.append(out[1])

        for m in module.modules():
            if isinstance(m, OcclusionAwareFusion):
                m.register_forward_hook(keep_blend)
        weights: dict[int, list] = {}
        with torch.no_grad():
            for batch in dm.test_dataloader():
                blends.clear()
                out = module.run(batch)
                if "occlusion" not in out:
                    print(f"{path}: this model has no occlusion detector")
                    break
                for level, m in enumerate(out["occlusion"]):
                    lit = resize_target(batch["lit"], m.shape[-2:])
                    masks.setdefault(level, []).append((m[:, 0].numpy(), lit.numpy()))
                for head, w in enumerate(blends):
                    lit = resize_target(batch["lit"], w.shape[-2:])
                    weights.setdefault(head, []).append((w.numpy(), lit.numpy()))
        print(path)
        for level, pairs in masks.items():
            m = np.concatenate([p[0].ravel() for p in pairs])
            lit = np.concatenate([p[1].ravel() for p in pairs]) > 0.5
            print(
                f"  level {level}: mask on lit {m[lit].mean():.3f}, on unlit "
                f"{m[~lit].mean():.3f}, AUC {auc(m, lit):.3f}"
            )
        for head, pairs in weights.items():
            print(f"  {HEADS[head]} fusion: {blend_summary(pairs)}")
    return 0
