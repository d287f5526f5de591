"""Calibrate a trained net's error bars and judge them:
``python -m odmv.study uncertainty RUN [RUN ...] [--score spread|steepness]``.

For each run folder (its best checkpoint): the score of every valid pixel of the validation
split (odmv.training.uncertainty: the phase head's fusion spread, else the predicted depth's
steepness) against its true error gives the split conformal factor at each coverage of
COVERAGES and the score below which the validation split kept 90 % of its pixels (``trusted``);
the test split then says how they hold: coverage and mean half width (mm) at each coverage,
the sparsification curve and AUSE, the MAE of the trusted pixels and their share, and the
share of scenes whose fringe contrast lies outside the calibration scenes' (the mean and spread
of the validation scenes' contrast are recorded: predict says when a capture lies outside) (with
``--heldout``, on the run's held-out set too: 200 scenes of its twin, rendered on first use,
as ``odmv.study heldout`` renders them; with ``--judge DATASET``, on that dataset's test split,
e.g. a shifted twin). All of it is
written to ``RUN/uncertainty.json``, which predict reads beside the checkpoint (an interval per
pixel, ``uncertainty.exr``, and the trusted mask).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from odmv.classical.fringe import period_in_camera_px
from odmv.io.atomic import write_json
from odmv.io.runfolder import METRICS, UNCERTAINTY, portable, recorded_dataset
from odmv.study.heldout import heldout_dataset
from odmv.study.records import checkpoint_data
from odmv.training.checkpoint import checkpoint_path
from odmv.training.evaluation import checkpoint_datamodule
from odmv.training.uncertainty import (
    COVERAGES,
    SCORES,
    ause_mm,
    conformal_scale,
    covered,
    default_score,
    fringe_contrast,
    outside_calibration,
    period_window_px,
    pixel_score,
    sparsification,
)

KEEP = 0.9  # the share of the validation pixels the trusted mask keeps
MIN_SCENES = 5  # validation scenes below which their contrast's spread is not recorded


def split_errors(module, loader, kind: str, window_px: int):
    """|error| (mm) and score of every valid pixel of ``loader``'s scenes, and each scene's
    fringe contrast."""
    errors, scores, contrasts = [], [], []
    with torch.no_grad():
        for batch in loader:
            out = module.run(batch)
            depth = module.depth_mm(out)
            valid = (batch["valid"] > 0) & torch.isfinite(batch["depth_mm"])
            errors.append((depth - batch["depth_mm"]).abs()[valid].numpy())
            scores.append(pixel_score(out, depth, kind)[valid].numpy())
            linear = module.norm.intensity(batch["fringes"].float())
            contrasts.append(fringe_contrast(linear, window_px).numpy())
    return np.concatenate(errors), np.concatenate(scores), np.concatenate(contrasts)


def contrast_window(module, dm) -> int:
    """A fringe period of the net's fringe in the camera (px, odd), where the rig is known."""
    spec, rig = module.hparams.input_spec or {}, dm.manifest.rig
    if rig is None or spec.get("period_px") is None:
        return 5
    cam = rig.camera_at(dm.spec.width_px, dm.spec.height_px)
    proj = rig.projectors()[module.hparams.views[0]]
    return period_window_px(period_in_camera_px(spec["period_px"], cam, proj))


def calibrate(module, dm, kind: str, judges: dict | None = None) -> dict:
    """The calibration of the module docstring on ``dm``'s validation split, judged on its
    test split and on the test split of each of ``judges`` (name -> data module)."""
    window = contrast_window(module, dm)
    cal_err, cal_score, cal_contrast = split_errors(module, dm.val_dataloader(), kind, window)
    factors = {c: conformal_scale(cal_err, cal_score, c)[None] for c in COVERAGES}
    trust = float(np.quantile(cal_score, KEEP))
    record = {
        "score": kind,
        "factor": {str(c): q for c, q in factors.items()},
        "trusted_score_mm": trust,
        "calibrated_on": {"split": "val", "pixels": int(cal_err.size)},
        # the validation scenes' fringe contrast, where there are enough to tell its spread
        "contrast": {
            "mean": float(np.nanmean(cal_contrast)),
            "std": float(np.nanstd(cal_contrast)),
            "window_px": window,
        }
        if np.isfinite(cal_contrast).sum() >= MIN_SCENES
        else None,
    }
    for name, data in {"test": dm, **(judges or {})}.items():
        err, score, contrast = split_errors(module, data.test_dataloader(), kind, window)
        record[name] = judged(err, score, factors, trust)
        flagged = [outside_calibration(float(c), record) is not None for c in contrast]
        record[name]["outside_calibration_share"] = float(np.mean(flagged))
    return record


def judged(err: np.ndarray, score: np.ndarray, factors: dict, trust: float) -> dict:
    """How a calibration holds on pixels it was not made on."""
    curve = sparsification(err, score)
    trusted = score <= trust
    return {
        "pixels": int(err.size),
        "mae_mm": float(err.mean()),
        "coverage": {str(c): covered(err, q * score) for c, q in factors.items()},
        "half_width_mm": {str(c): float(np.mean(q * score)) for c, q in factors.items()},
        "trusted_share": float(trusted.mean()),
        "trusted_mae_mm": float(err[trusted].mean()) if trusted.any() else None,
        "ause_mm": ause_mm(curve),
        "sparsification": curve,
    }


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(
        prog="python -m odmv.study uncertainty", description=__doc__.splitlines()[0]
    )
    ap.add_argument("runs", nargs="+", type=Path, help="run folders (their best checkpoint)")
    ap.add_argument("--score", choices=SCORES, help="default: the best the net's output has")
    ap.add_argument("--heldout", action="store_true", help="judge it on the run's held-out set too")
    ap.add_argument(
        "--judge", type=Path, action="append", default=[], help="and on this dataset's test split"
    )
    args = ap.parse_args(argv)
    for run in args.runs:
        if not (run / METRICS).is_file():
            raise ValueError(f"{run}: not a finished run (no {METRICS})")
        ckpt = checkpoint_path(run)
        module, dm = checkpoint_data(ckpt, None)
        judges = {}
        if args.heldout:  # rendered on first use, as odmv.study heldout renders it
            root = heldout_dataset(recorded_dataset(json.loads((run / METRICS).read_text()), run))
            judges["heldout"] = checkpoint_datamodule(module, "test", root=str(root))
        for root in args.judge:  # e.g. a shifted twin of odmv.study robustness
            judges[portable(root)] = checkpoint_datamodule(module, "test", root=str(root))
        record = calibrate(module, dm, args.score or default_score(module.phase_head), judges)
        record["checkpoint"] = portable(ckpt, run)
        write_json(run / UNCERTAINTY, record)
        for name in ("test", *judges):
            t = record[name]
            print(
                f"{run} on {name}: {record['score']}; covered on {t['coverage']['0.9']:.3f} at "
                f"0.9 (half width {t['half_width_mm']['0.9']:.3f} mm); trusted "
                f"{t['trusted_share']:.1%} at MAE {t['trusted_mae_mm']:.4f} mm of "
                f"{t['mae_mm']:.4f}; AUSE {t['ause_mm']:.4f}; scenes outside the "
                f"calibration {t['outside_calibration_share']:.0%}"
            )
        print(f"  -> {run / UNCERTAINTY}")
