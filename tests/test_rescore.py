import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from odmv.study import rescore

NEW = ("first_unlit", "first_shadowed")


def _older(run: Path, tmp_path: Path) -> Path:
    """A copy of ``run`` as a run trained before the first-view subsets existed."""
    old = tmp_path / "old"
    shutil.copytree(run, old)
    metrics = json.loads((old / "metrics.json").read_text())
    (old / "metrics.json").write_text(
        json.dumps({k: v for k, v in metrics.items() if not k.endswith(NEW)})
    )
    rows = list(csv.DictReader((old / "test_scenes.csv").open()))
    with (old / "test_scenes.csv").open("w", newline="") as fh:
        keep = [k for k in rows[0] if not k.endswith(NEW)]
        w = csv.DictWriter(fh, fieldnames=keep, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return old


def test_rescore_adds_the_metrics_a_run_was_trained_without(trained, tmp_path):
    run, metrics = trained
    old = _older(run, tmp_path)
    added = rescore.rescore(old)
    assert sorted(added) == sorted(k for k in metrics if k.startswith("test/") and k.endswith(NEW))
    again = json.loads((old / "metrics.json").read_text())
    for k in added:  # what the test step itself logged
        assert again[k] == pytest.approx(metrics[k], rel=1e-6), k
    mine = list(csv.DictReader((run / "test_scenes.csv").open()))
    theirs = list(csv.DictReader((old / "test_scenes.csv").open()))
    assert list(theirs[0]) == list(mine[0])
    for a, b in zip(mine, theirs, strict=True):
        for k in a:
            assert (
                a[k] == b[k]
                if k in ("scene", "family")
                else float(a[k]) == pytest.approx(float(b[k]), rel=1e-9, abs=1e-12)
            ), k
    assert rescore.rescore(old) == []  # nothing more to add


def test_rescore_refuses_predictions_that_do_not_give_the_stored_metrics(trained, tmp_path):
    run, _ = trained
    old = _older(run, tmp_path)
    before = (old / "metrics.json").read_text()
    with np.load(old / "test_predictions.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["pred_mm"] = arrays["pred_mm"] + 0.5  # another net's predictions
    np.savez_compressed(old / "test_predictions.npz", **arrays)
    with pytest.raises(SystemExit, match="test/mae_mm is .* not the run's predictions"):
        rescore.rescore(old)
    assert (old / "metrics.json").read_text() == before
