"""Does a phase-head net (``head=phase``) decode the fringes? Each view's phase, fringe order
and confidence against the twin's truth on a checkpoint's test split.

    python -m odmv.study phase CKPT [CKPT ...] [--split val|test]

Prints, per checkpoint: the MAE (mm) of the fused depth and of the net's own regressed depth,
and the share of the fusion's weight on the regressed depth; then per view, on the pixels its
projector lights: the wrapped phase's median error (rad), the share whose fringe order is right
(the decoded offset within half a period of the truth), the view's depth MAE (mm) where its
order is right and overall, the share of the fused depth's weight the view gets where it is lit
and where it is not, and the confidence's ROC AUC as a lit/unlit detector (1: separates them
perfectly; 0.5: no information). Last, where the wrong orders lie: their share of the lit
pixels, how many of them are within a pixel of a depth edge (a step over 1 mm to a neighbour),
the wrong share among lit pixels more than 8 mm above the plane, and the share of lit pixels
where the regressed depth, which the order comes from, is more than half a period off.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from odmv.classical.geometry import offset_from_coord, offset_from_depth
from odmv.study.ocd import auc
from odmv.study.records import checkpoint_data
from odmv.training.checkpoint import CheckpointError


def phase_scores(module, loader) -> dict:
    """The figures of the module docstring over ``loader``'s batches."""
    acc: dict[str, list] = {}

    def keep(name, value):
        acc.setdefault(name, []).append(np.asarray(value))

    with torch.no_grad():
        for batch in loader:
            out = module.run(batch)
            valid = torch.isfinite(batch["depth_mm"])[:, 0]
            truth = batch["depth_mm"][:, 0]
            keep("fused", (module.depth_mm(out)[:, 0] - truth).abs()[valid])
            keep("regressed", (module.depth_mm({"depth": out["regressed"]})[:, 0] - truth)[valid])
            keep("regressed_weight", out["weights"][:, -1][valid])
            maps = batch["calibration"]
            coord = batch["projector_coord"].nan_to_num(0.0)
            # the order is right where the decoded offset lies within half a period of the truth
            decoded = torch.cat(
                [
                    offset_from_depth(d[:, None], maps[:, v : v + 1])
                    for v, d in enumerate(out["view_depth_mm"].unbind(1))
                ],
                1,
            )
            off = (decoded - offset_from_coord(coord, maps)).abs() < maps[:, :, 1] / 2
            sc = out["phase"].unflatten(1, (maps.shape[1], 2))
            tc = batch["phase_target"].unflatten(1, (maps.shape[1], 2))
            dphi = torch.atan2(sc[:, :, 0], sc[:, :, 1]) - torch.atan2(tc[:, :, 0], tc[:, :, 1])
            dphi = torch.remainder(dphi + torch.pi, 2 * torch.pi) - torch.pi
            err = (out["view_depth_mm"] - batch["depth_mm"]).abs()
            truth_off = offset_from_coord(coord, maps)
            coarse = offset_from_depth(module.depth_mm({"depth": out["regressed"]}), maps)
            gy, gx = torch.gradient(truth[:, None].nan_to_num(0.0)[:, 0], dim=(-2, -1))
            step = (torch.maximum(gx.abs(), gy.abs()) > 1.0).float()[:, None]
            edge = torch.nn.functional.max_pool2d(step, 3, 1, 1)[:, 0] > 0
            tall = truth.nan_to_num(float("-inf")).amax((-2, -1), keepdim=True) - truth > 8.0
            for v in range(maps.shape[1]):
                lit = batch["lit"][:, v] > 0.5
                keep(f"phase{v}", dphi[:, v][lit].abs())
                right = off[:, v][lit]
                keep(f"order{v}", right)
                keep(f"depth{v}", err[:, v][lit])
                keep(f"depth_right{v}", err[:, v][lit][right])
                keep(f"weight_lit{v}", out["weights"][:, v][lit])
                keep(f"weight_unlit{v}", out["weights"][:, v][~lit])
                keep(f"conf{v}", out["confidence"][:, v].flatten())
                keep(f"lit{v}", lit.flatten())
                keep("wrong", ~right)
                keep("wrong_edge", edge[lit])
                keep("tall_wrong", ~off[:, v][lit & tall])
                far = (coarse[:, v] - truth_off[:, v]).abs() > maps[:, v, 1] / 2
                keep("coarse_far", far[lit])
    return {k: np.concatenate([np.ravel(x) for x in v]) for k, v in acc.items()}


def report(path: str, module, scores: dict) -> list[str]:
    views = list(module.hparams.views)
    lines = [
        f"{path}: fused MAE {scores['fused'].mean():.4f} mm, regressed "
        f"{np.abs(scores['regressed']).mean():.4f} mm; weight on the regressed depth "
        f"{scores['regressed_weight'].mean():.3f}"
    ]
    for v, name in enumerate(views):
        unlit = scores[f"weight_unlit{v}"]
        lines.append(
            f"  {name}: phase error median {np.median(scores[f'phase{v}']):.3f} rad, order right "
            f"{scores[f'order{v}'].mean():.1%}, depth MAE {scores[f'depth_right{v}'].mean():.4f} "
            f"mm where right ({scores[f'depth{v}'].mean():.4f} overall), weight lit "
            f"{scores[f'weight_lit{v}'].mean():.3f} / unlit "
            f"{unlit.mean() if unlit.size else float('nan'):.3f}, confidence AUC "
            f"{auc(scores[f'conf{v}'], scores[f'lit{v}']):.3f}"
        )
    wrong = scores["wrong"]
    lines.append(
        f"  wrong orders: {wrong.mean():.2%} of the lit pixels, "
        f"{scores['wrong_edge'][wrong].mean():.0%} of them at depth edges; "
        f"{scores['tall_wrong'].mean():.0%} of the lit pixels above 8 mm; the regressed depth "
        f"is more than half a period off on {scores['coarse_far'].mean():.2%} of the lit pixels"
    )
    return lines


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoints", nargs="+", metavar="CKPT")
    parser.add_argument("--split", default="test", choices=("val", "test"))
    args = parser.parse_args(argv)
    for path in args.checkpoints:
        try:
            module, dm = checkpoint_data(path, "fit" if args.split == "val" else "test")
        except CheckpointError as e:
            raise SystemExit(f"error: {e}") from None
        if not module.phase_head:
            raise SystemExit(f"error: {path}: the net has no phase head (head=phase)")
        scores = phase_scores(module, dm._loader(args.split, shuffle=False))
        print("\n".join(report(path, module, scores)), flush=True)
    return 0
