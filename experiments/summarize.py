"""Compare groups of finished runs: mean ± std over seeds, overall, shadowed and per family.

    python experiments/summarize.py 'BN=outputs/accuracy/bn-*' 'GN=outputs/accuracy/gn-*'

Each argument is ``LABEL=GLOB`` (run folders holding metrics.json, and test_scenes.csv for the
per-scene columns: a committed reproduction record keeps only metrics.json). Prints a markdown
table: runs, test MAE / RMSE over all pixels, MAE over shadowed pixels, MAE per scene family,
and the worst scene of each run (to find outliers before trusting a mean).
"""

from __future__ import annotations

import csv
import glob
import json
import sys
from pathlib import Path

import numpy as np


def _stat(values: list[float]) -> str:
    v = np.array([x for x in values if np.isfinite(x)], float)
    if not len(v):
        return "–"
    return f"{v.mean():.3f}" + (f" ± {v.std(ddof=1):.3f}" if len(v) > 1 else "")


def run_groups(arg: str, marker: str) -> tuple[str, list[Path]]:
    """``LABEL=GLOB`` as the label and the matched run folders that hold ``marker``."""
    label, pattern = arg.rsplit("=", 1)  # labels may hold "=" (S=4), globs do not
    return label, sorted(Path(p) for p in glob.glob(pattern) if (Path(p) / marker).is_file())


def main(args: list[str]) -> int:
    if not args or any("=" not in a for a in args):
        print(__doc__, file=sys.stderr)
        return 2
    families = ("primitives", "pcb", "freeform")
    print(
        "| variant | runs | MAE (mm) | RMSE (mm) | MAE shadowed (mm) | "
        + " | ".join(f"MAE {f} (mm)" for f in families)
        + " | worst scene (MAE mm) |"
    )
    print("|---|---:|" + "---:|" * (4 + len(families)))
    for arg in args:
        label, folders = run_groups(arg, "metrics.json")
        m = [json.loads((f / "metrics.json").read_text()) for f in folders]
        per_family: dict[str, list[float]] = {f: [] for f in families}
        worst = []
        for f in folders:
            scenes = f / "test_scenes.csv"
            if not scenes.is_file():  # per-scene figures unknown: that run leaves them out
                continue
            rows = list(csv.DictReader(scenes.open()))
            for fam in families:
                errs = [float(r["mae_mm"]) for r in rows if r["family"] == fam]
                per_family[fam].append(float(np.mean(errs)) if errs else np.nan)
            w = max(rows, key=lambda r: float(r["mae_mm"]))
            worst.append(f"{w['scene']} {w['family']} {float(w['mae_mm']):.2f}")
        cols = [
            label,
            str(len(m)),
            _stat([x["test/mae_mm"] for x in m]),
            _stat([x["test/rmse_mm"] for x in m]),
            _stat([x["test/mae_mm_shadowed"] for x in m]),
            *(_stat(per_family[f]) for f in families),
            "; ".join(worst) or "–",
        ]
        print("| " + " | ".join(cols) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
