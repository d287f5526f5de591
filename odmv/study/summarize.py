"""Compare groups of finished runs: mean ± std over seeds, overall, shadowed and per family.

    python -m odmv.study summarize 'BN=outputs/accuracy/bn-*' 'GN=outputs/accuracy/gn-*'

Each argument is ``LABEL=GLOB`` (run folders holding metrics.json, and test_scenes.csv for the
per-scene columns: a committed reproduction record keeps only metrics.json). Prints a markdown
table: runs, test MAE / RMSE over all pixels, MAE over shadowed pixels, over interior pixels
and over the edge band (odmv.training.metrics; "–" for records before them), held-out MAE and
its interior (where the runs were scored there), MAE per scene family, and the worst scene of
each run (to find outliers before trusting a mean).
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from odmv.io.runfolder import HELDOUT, METRICS, SCENES_CSV
from odmv.study.records import run_groups


def _stat(values: list[float]) -> str:
    v = np.array([x for x in values if np.isfinite(x)], float)
    if not len(v):
        return "–"
    return f"{v.mean():.3f}" + (f" ± {v.std(ddof=1):.3f}" if len(v) > 1 else "")


FAMILIES = ("primitives", "pcb", "freeform")


def summary_lines(groups: list[tuple[str, list[Path]]]) -> list[str]:
    """The markdown table of labelled groups of finished run folders."""
    lines = [
        "| variant | runs | MAE (mm) | RMSE (mm) | MAE shadowed (mm) | MAE interior (mm) | "
        "MAE edge (mm) | held-out MAE (mm) | held-out MAE interior (mm) | "
        + " | ".join(f"MAE {f} (mm)" for f in FAMILIES)
        + " | worst scene (MAE mm) |",
        "|---|---:|" + "---:|" * (8 + len(FAMILIES)),
    ]
    for label, folders in groups:
        m = [json.loads((f / METRICS).read_text()) for f in folders]
        held = [json.loads((f / HELDOUT).read_text()) for f in folders if (f / HELDOUT).is_file()]
        per_family: dict[str, list[float]] = {f: [] for f in FAMILIES}
        worst = []
        for f in folders:
            scenes = f / SCENES_CSV
            if not scenes.is_file():  # per-scene figures unknown: that run leaves them out
                continue
            rows = list(csv.DictReader(scenes.open()))
            for fam in FAMILIES:
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
            _stat([x.get("test/mae_mm_interior", np.nan) for x in m]),
            _stat([x.get("test/mae_mm_edge", np.nan) for x in m]),
            _stat([x["test/mae_mm"] for x in held]),
            _stat([x.get("test/mae_mm_interior", np.nan) for x in held]),
            *(_stat(per_family[f]) for f in FAMILIES),
            "; ".join(worst) or "–",
        ]
        lines.append("| " + " | ".join(cols) + " |")
    return lines


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("groups", nargs="+", metavar="LABEL=GLOB")
    args = ap.parse_args(argv).groups
    if any("=" not in a for a in args):
        ap.error("each argument is LABEL=GLOB")
    print("\n".join(summary_lines([run_groups(arg, METRICS) for arg in args])))
    return 0
