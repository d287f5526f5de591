"""The calibration check of the classical target, on datasets with their full sequences: each
projector's phase-shifting depth against the views' per-pixel median, averaged over the scenes
(what ``adapt=true`` with ``adaptation.target=classical`` refuses above
``adaptation.stale_mm``; odmv.data.classical.classical_depths, docs/robustness.md).

    python experiments/calibration_check.py data/adapt100-seed3-*-full-* --size 64

Per dataset: each view's mean deviation (mm), their spread (population std, mm), the share of
pixels the fused reconstruction covers, and the seconds it took. Reads no labels.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from odmv.data.classical import classical_depths
from odmv.io.manifest import load_manifest
from odmv.training.adaptation import view_spread_mm


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("datasets", nargs="+", help="dataset folders with images=full")
    parser.add_argument("--size", type=int, default=64, help="the net's size (px, square)")
    args = parser.parse_args()
    print("| dataset | views' deviation (mm) | spread (mm) | covered | s |")
    print("|---|---|---:|---:|---:|")
    for root in args.datasets:
        t0 = time.perf_counter()
        m = load_manifest(root)
        depths, offsets = classical_depths(m, [s["id"] for s in m.scenes], (args.size,) * 2)
        spread = view_spread_mm(offsets)
        covered = float(np.mean([np.isfinite(d).mean() for d in depths.values()]))
        shown = ", ".join(f"{v} {x:+.4f}" for v, x in offsets.items())
        seconds = time.perf_counter() - t0
        print(f"| {m.root.name} | {shown} | {spread:.4f} | {covered:.2f} | {seconds:.0f} |")


if __name__ == "__main__":
    main()
