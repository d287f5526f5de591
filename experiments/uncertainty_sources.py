"""Which per-pixel score ranks a trained net's depth errors best: a measurement, not a test.

    python experiments/uncertainty_sources.py CKPT [--other CKPT] [--dataset DIR]

For every valid pixel of the test split (of CKPT's dataset, or of ``--dataset`` with the same
rig and fringe) it prints, per candidate score: AUSE (mm x share kept; 0 ranks as the errors
do), the MAE of the 90 % of pixels the score trusts most against the MAE of all of them, and
the coverage on the test split of the 90 % interval calibrated on the validation split (split
conformal, odmv.training.uncertainty). Candidates: the predicted depth's own steepness (the
3 x 3 maximum of its gradient, mm per pixel; any net), the disagreement with a second seed
(``--other``), and with the phase head the fusion's spread over its candidates (each view's
triangulated depth and the regressed one, weighted by the blend; mm), its doubt (1 - the
largest weight), the fused depth's distance from the regressed one (mm), and the geometric
mean of the spread and the steepness.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from odmv.training.evaluation import checkpoint_datamodule  # noqa: E402
from odmv.training.module import load_module  # noqa: E402
from odmv.training.uncertainty import (  # noqa: E402
    TINY_MM,
    ause_mm,
    conformal_scale,
    covered,
    pixel_score,
    sparsification,
)


def phase_scores(out: dict, depth: torch.Tensor) -> dict[str, torch.Tensor]:
    """The phase head's own doubts (B x 1 x H x W)."""
    return {
        "fusion spread (mm)": pixel_score(out, depth, "spread"),
        "fusion doubt (1 - max weight)": 1 - out["weights"].amax(1, keepdim=True),
        "fused vs regressed (mm)": (depth - out["regressed_mm"]).abs(),
    }


def split_scores(module, other, dm, split: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """|error| (mm) and every candidate score over the valid pixels of ``split``."""
    errors, scores = [], {}
    loader = {"val": dm.val_dataloader, "test": dm.test_dataloader}[split]()
    with torch.no_grad():
        for batch in loader:
            out = module.run(batch)
            depth = module.depth_mm(out)
            valid = (batch["valid"] > 0) & torch.isfinite(batch["depth_mm"])
            found = {"depth steepness (mm/px)": pixel_score(out, depth, "steepness")}
            if "weights" in out:
                found |= phase_scores(out, depth)
            if "fusion spread (mm)" in found:  # both: a steep place the views disagree on
                found["spread x steepness"] = (
                    found["fusion spread (mm)"] * found["depth steepness (mm/px)"]
                ).sqrt()
            if other is not None:
                found["seed disagreement (mm)"] = (other.depth_mm(other.run(batch)) - depth).abs()
            errors.append((depth - batch["depth_mm"]).abs()[valid].numpy())
            for name, s in found.items():
                scores.setdefault(name, []).append(s.float()[valid].numpy())
    return np.concatenate(errors), {k: np.concatenate(v) + TINY_MM for k, v in scores.items()}


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("ckpt", type=Path)
    ap.add_argument("--other", type=Path, help="a second seed's checkpoint of the same row")
    ap.add_argument("--dataset", type=Path, help="score on this dataset's splits instead")
    ap.add_argument("--coverage", type=float, default=0.9)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    module = load_module(args.ckpt).eval()
    other = load_module(args.other).eval() if args.other else None
    changes = {"root": str(args.dataset)} if args.dataset else {}
    dm = checkpoint_datamodule(module, None, **changes)
    cal_err, cal = split_scores(module, other, dm, "val")
    err, scores = split_scores(module, other, dm, "test")
    oracle = sparsification(err, err)
    kept = oracle["share"].index(0.9)
    print(f"{args.ckpt} on {dm.root} (test: {err.size} pixels)")
    print(f"  MAE all pixels {err.mean():.4f} mm; oracle at 90 % kept {oracle['mae_mm'][kept]:.4f}")
    print(f"  {'score':32s} {'AUSE':>8s} {'MAE@90%':>8s} {'ratio':>6s} {'cover':>6s} {'width':>7s}")
    for name, s in scores.items():
        curve = sparsification(err, s)
        q = conformal_scale(cal_err, cal[name], args.coverage)[None]
        print(
            f"  {name:32s} {ause_mm(curve):8.4f} {curve['mae_mm'][kept]:8.4f} "
            f"{curve['mae_mm'][kept] / err.mean():6.3f} {covered(err, q * s):6.3f} "
            f"{np.mean(q * s):7.3f}"
        )


if __name__ == "__main__":
    main(sys.argv[1:])
