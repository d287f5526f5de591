"""Score finished runs with today's metrics, from their saved test predictions.

    python -m odmv.study rescore outputs/reproduce/mini/odmvnet-s1-multitask-seed1 ...

A run's test_predictions.npz holds its prediction (mm) of every test scene, so a metric added
after it was trained (a pixel subset such as first_unlit) follows from those predictions and
the test split's ground truth, without the net. The run's data settings (from its best
checkpoint) select the split; the subsets are today's. The metrics the run has are computed
again first, as a check: they must agree to 1e-5, or the predictions or the dataset are not
the run's, and nothing is written. The new ones are added to metrics.json and
test_scenes.csv (atomically; the rest stays as it was). A reproduction copies the updated run
into its record on its next call.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import numpy as np
import torch

from odmv.io.atomic import write_json
from odmv.io.runfolder import METRICS, PREDICTIONS, SCENES_CSV
from odmv.study.records import run_data
from odmv.training.metrics import SUBSETS, DepthErrors, per_image_subset_errors, subset_results
from odmv.training.module import subset_masks, write_scene_rows


def rescore(run: Path) -> list[str]:
    """Add today's test metrics that ``run`` lacks; returns their names."""
    path = run / PREDICTIONS
    if not path.is_file():
        raise SystemExit(f"error: {run}: no {PREDICTIONS} (a record keeps only some scenes)")
    _, dm = run_data(run, "test")
    with np.load(path) as z:
        preds = dict(zip((str(s) for s in z["scene_id"]), z["pred_mm"], strict=True))
    errors = {k: DepthErrors() for k in SUBSETS}
    rows = []
    for batch in dm.test_dataloader():
        ids = list(batch["scene_id"])
        if missing := [s for s in ids if s not in preds]:
            raise SystemExit(f"error: {path}: no prediction of test scene {missing[0]}")
        pred = torch.from_numpy(np.stack([preds[s] for s in ids]))[:, None]
        masks = subset_masks(batch)
        for k, mask in masks.items():
            errors[k].update(pred, batch["depth_mm"], mask)
        per = per_image_subset_errors(pred, batch["depth_mm"], masks)
        for i, sid in enumerate(ids):
            row = {"scene": sid, "family": batch["family"][i]}
            rows.append(row | {k: float(v[i]) for k, v in per.items()})
    # stored as the trainer logs them: float32
    new = {
        k: float(np.float32(v))
        for k, v in subset_results("test", {k: e.compute() for k, e in errors.items()}).items()
    }
    metrics = json.loads((run / METRICS).read_text())
    for k, v in new.items():
        if k in metrics and not math.isclose(v, metrics[k], rel_tol=1e-5, abs_tol=1e-9):
            raise SystemExit(
                f"error: {run}: {k} is {metrics[k]} in metrics.json but {v} from its "
                f"{PREDICTIONS}: not the run's predictions or dataset; nothing written"
            )
    added = [k for k in new if k not in metrics]
    with (run / SCENES_CSV).open() as fh:
        old_columns = next(csv.reader(fh))
    if added or set(rows[0]) - set(old_columns):
        write_scene_rows(run, rows)
        write_json(run / METRICS, metrics | {k: new[k] for k in added})
    return added


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="finished run folders")
    for run in ap.parse_args(argv).runs:
        added = rescore(run)
        print(f"{run}: " + (f"added {', '.join(added)}" if added else "nothing to add"))
