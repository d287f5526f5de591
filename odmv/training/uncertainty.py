"""Per-pixel error bars and how to judge them (numpy; depths and errors in mm).

A net's uncertainty is a score per pixel that should rank its errors: larger where the depth
is worse. Split conformal calibration (:func:`conformal_scale`) turns it into an interval
without trusting the model: on held-back scenes with ground truth, the normalized errors
|error| / score give the factor q whose interval ``depth ± q x score`` holds the truth on the
asked share of pixels (``coverage``); the same factor then serves every later capture, as long
as it resembles the calibration scenes. Pixels of one scene are not exchangeable with each
other, scenes are: the guarantee is marginal over pixels of scenes drawn like the calibration
ones. Mondrian calibration (``groups``: a scene family, a height band) gives each group its
own factor where one factor would cover some groups too much and others too little.

How well the score ranks the errors, whatever its scale: the sparsification curve
(:func:`sparsification`), the MAE of the pixels kept when the most uncertain are dropped first,
against the oracle that drops the largest true errors first; AUSE (:func:`ause_mm`) is the area
between them (0: the score ranks errors perfectly; a random ranking leaves the MAE flat).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from odmv.io.runfolder import UNCERTAINTY
from odmv.training.configs import run_folder_of

#: shares of the pixels kept at which the sparsification curve is read (the last: all of them)
KEPT_SHARES = tuple(np.round(np.arange(0.05, 1.0001, 0.05), 2))
#: the coverages a calibration holds a factor for (predict's ``coverage=`` picks one)
COVERAGES = (0.5, 0.8, 0.9, 0.95, 0.99)
#: the scores a net's own output gives (experiments/results/uncertainty/notebook.md, round 1):
#: the phase head's fusion spread ranks its errors best; the predicted depth's steepness is
#: every net's
SCORES = ("spread", "steepness")
TINY_MM = 1e-6  # a floor under every score: a zero score gives no interval to scale


def calibration_of(ckpt: Path) -> dict | None:
    """The error bars' calibration of the run a checkpoint is the best of (its
    ``uncertainty.json``, odmv.study.uncertainty), if it has one for this very checkpoint."""
    run = run_folder_of(ckpt)
    path = run / UNCERTAINTY if run is not None else None
    if path is None or not path.is_file():
        return None
    bars = json.loads(path.read_text())
    return bars if (run / bars.get("checkpoint", "")).resolve() == Path(ckpt).resolve() else None


#: a scene's fringes are outside its calibration beyond this many standard deviations of the
#: calibration scenes' contrast (defocus 1.5 px: every scene; the nominal twin: none; notebook
#: round 5)
CONTRAST_Z = 3.0
LIT = 0.1  # a pixel whose brightest value within a window exceeds this (full scale) is lit


def period_window_px(period_camera_px: float) -> int:
    """The odd window (px) that spans one fringe period in the camera: within it a lit pixel
    sees a bright fringe and its contrast is the fringe's."""
    return 2 * math.ceil(period_camera_px / 2) + 1


def fringe_contrast(images: torch.Tensor, window_px: int) -> torch.Tensor:
    """Each scene's fringe contrast (B,): the median over its lit pixels, in every view, of the
    Michelson contrast (max - min) / (max + min) within ``window_px`` (a fringe period in the
    camera) of linear-intensity images (B x S x H x W). It falls under defocus and blur, whatever
    the surface's albedo, where the net's error bars stop holding."""
    k = max(3, window_px | 1)
    hi = F.max_pool2d(images.float(), k, 1, k // 2)
    lo = -F.max_pool2d(-images.float(), k, 1, k // 2)
    contrast = (hi - lo) / (hi + lo).clamp_min(1e-3)
    lit = hi > LIT
    return torch.stack(
        [
            c[m].median() if m.any() else c.new_tensor(math.nan)
            for c, m in zip(contrast, lit, strict=True)
        ]
    )


def outside_calibration(contrast: float, bars: dict) -> str | None:
    """Why a scene's fringes lie outside what the error bars were calibrated on (its contrast
    against the calibration scenes'), or None."""
    ref = bars.get("contrast")
    if ref is None or not math.isfinite(contrast):
        return None
    z = (contrast - ref["mean"]) / max(ref["std"], 1e-6)
    if abs(z) <= CONTRAST_Z:
        return None
    return (
        f"fringe contrast {contrast:.3f} against the calibration scenes' {ref['mean']:.3f} ± "
        f"{ref['std']:.3f} ({z:+.1f} sigma): its error bars may not hold (defocus, blur or "
        "another exposure than the calibration's)"
    )


def capture_outside(images: np.ndarray, bars: dict) -> str | None:
    """:func:`outside_calibration` of one capture's linear-intensity images (S x H x W); None
    where the calibration recorded no contrast (too few scenes to tell its spread)."""
    ref = bars.get("contrast")
    if ref is None:
        return None
    batch = torch.from_numpy(np.asarray(images, np.float32)[None])
    return outside_calibration(float(fringe_contrast(batch, ref["window_px"])[0]), bars)


def default_score(phase_head: bool) -> str:
    """The score a net is calibrated with unless told: the best its output has."""
    return "spread" if phase_head else "steepness"


def pixel_score(out: dict, depth_mm: torch.Tensor, kind: str) -> torch.Tensor:
    """The uncertainty score (B x 1 x H x W, mm) of a net's output: ``spread``, the blend's
    weighted spread of its candidates (each view's triangulated depth and the regressed one)
    around the fused depth (phase head); ``steepness``, the 3 x 3 maximum of the predicted
    depth's gradient (mm per pixel: where depth jumps, a net errs)."""
    if kind == "spread":
        if "weights" not in out:
            raise ValueError("uncertainty score spread: the net has no phase head (use steepness)")
        candidates = torch.cat([out["view_depth_mm"], out["regressed_mm"]], 1).float()
        gap = torch.nan_to_num(candidates) - depth_mm
        score = (out["weights"].float() * gap**2).sum(1, keepdim=True).sqrt()
    elif kind == "steepness":  # central differences, the border replicated (ONNX exports it)
        d = F.pad(depth_mm.float(), (1, 1, 1, 1), mode="replicate")
        gx = (d[..., 1:-1, 2:] - d[..., 1:-1, :-2]) / 2
        gy = (d[..., 2:, 1:-1] - d[..., :-2, 1:-1]) / 2
        score = F.max_pool2d(torch.sqrt(gx**2 + gy**2), 3, stride=1, padding=1)
    else:
        raise ValueError(f"uncertainty score {kind!r} unknown; choose {' or '.join(SCORES)}")
    return score.clamp_min(TINY_MM)


def _flat(*arrays) -> list[np.ndarray]:
    """The pixels where every array is finite, flattened (float64)."""
    stacked = [np.asarray(a, np.float64).ravel() for a in arrays]
    ok = np.logical_and.reduce([np.isfinite(a) for a in stacked])
    return [a[ok] for a in stacked]


def conformal_scale(
    abs_err_mm: np.ndarray, score: np.ndarray, coverage: float, groups: np.ndarray | None = None
) -> dict:
    """The factor q per group (``{None: q}`` without ``groups``) such that |error| <= q x score
    on at least ``coverage`` of the calibration pixels: the ceil((n + 1) c)-th smallest of the
    normalized errors |error| / score (split conformal, with its finite-sample correction);
    inf where a group has too few pixels to promise ``coverage``. Scores must be positive."""
    if not 0 < coverage < 1:
        raise ValueError(f"coverage={coverage}: a share between 0 and 1")
    keys = np.zeros(np.shape(abs_err_mm), np.int64) if groups is None else np.asarray(groups)
    err, s, g = _flat(abs_err_mm, score, keys)
    if np.any(s <= 0):
        raise ValueError("uncertainty scores must be positive to scale an interval")
    out = {}
    for key in np.unique(g):
        ratio = np.sort(err[g == key] / s[g == key])
        rank = math.ceil((len(ratio) + 1) * coverage)
        q = float(ratio[rank - 1]) if rank <= len(ratio) else math.inf
        out[None if groups is None else key.item()] = q
    return out


def covered(abs_err_mm: np.ndarray, half_width_mm: np.ndarray) -> float:
    """The share of pixels whose true depth lies within the interval (|error| <= half width)."""
    err, half = _flat(abs_err_mm, half_width_mm)
    return float(np.mean(err <= half)) if err.size else math.nan


def sparsification(abs_err_mm: np.ndarray, score: np.ndarray, shares=KEPT_SHARES) -> dict:
    """The MAE (mm) of the pixels kept at each share of ``shares``, the most uncertain dropped
    first (``score``; ties dropped in pixel order), and of the oracle that drops the largest
    errors first; a random ranking's expectation is the all-pixel MAE at every share."""
    err, s = _flat(abs_err_mm, score)
    if not err.size:
        raise ValueError("no pixel with both an error and a score")
    by_score = err[np.argsort(s, kind="stable")]
    by_error = np.sort(err)
    kept = [max(1, round(share * err.size)) for share in shares]
    return {
        "share": [float(x) for x in shares],
        "mae_mm": [float(by_score[:k].mean()) for k in kept],
        "oracle_mm": [float(by_error[:k].mean()) for k in kept],
        "random_mm": float(err.mean()),
    }


def ause_mm(curve: dict) -> float:
    """Area between a sparsification curve and its oracle over the shares kept (mm x share,
    the trapezoid rule): 0 where the score ranks the errors as the errors themselves do."""
    x = np.asarray(curve["share"])
    gap = np.asarray(curve["mae_mm"]) - np.asarray(curve["oracle_mm"])
    return float(np.sum((gap[1:] + gap[:-1]) / 2 * np.diff(x)))
