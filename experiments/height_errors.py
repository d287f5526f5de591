"""Test MAE by height above the base plane: where in depth the error of finished runs lies.

    python experiments/height_errors.py 'UNet=outputs/reproduce/mini/unet-s1-seed*' ...

Each argument is ``LABEL=GLOB`` (run folders holding test_predictions.npz). Heights are in mm
above the base plane, taken as the largest ground-truth depth of the test split (the plane
is the farthest surface the camera sees). Prints a markdown table: the share of valid pixels
in each height band, then per label the MAE in each band, mean ± std over the matched runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from summarize import run_groups  # this folder's sibling script: the same LABEL=GLOB rule

BANDS_MM = [0.0, 0.5, 2.0, 5.0, 8.0, 12.0, np.inf]


def band_errors(folder: Path, bands: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """Per band: MAE (mm) and the share of valid pixels, for one run's test predictions."""
    with np.load(folder / "test_predictions.npz") as z:
        pred, depth = z["pred_mm"], z["depth_mm"]
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("groups", nargs="+", metavar="LABEL=GLOB")
    args = ap.parse_args()
    names = [
        f"{lo:g}-{hi:g} mm" if np.isfinite(hi) else f"> {lo:g} mm"
        for lo, hi in zip(BANDS_MM[:-1], BANDS_MM[1:], strict=True)
    ]
    rows, share = [], None
    for group in args.groups:
        label, folders = run_groups(group, "test_predictions.npz")
        if not folders:
            raise SystemExit(f"error: {group}: no finished runs (no test_predictions.npz)")
        results = [band_errors(f, BANDS_MM) for f in folders]
        share = results[0][1]
        mae = np.stack([r[0] for r in results])
        std = mae.std(axis=0, ddof=1) if len(mae) > 1 else np.zeros(mae.shape[1])
        cells = [f"{m:.2f} ± {s:.2f}" for m, s in zip(mae.mean(axis=0), std, strict=True)]
        rows.append(f"| {label} | {len(folders)} | " + " | ".join(cells) + " |")
    print("| MAE (mm) by height above the plane | runs | " + " | ".join(names) + " |")
    print("|---|---:|" + "---:|" * len(names))
    print("| share of valid pixels | – | " + " | ".join(f"{s * 100:.1f} %" for s in share) + " |")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
