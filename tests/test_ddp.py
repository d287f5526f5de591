"""Two-process DDP on the CPU (gloo): one process writes the run's files, and the test metrics
count each scene once, equal to a single-process evaluation of the same checkpoint."""

import csv
import json
import subprocess
import sys

import pytest
from helpers import compose_config

from odmv.sim.writer import SimSettings, simulate
from odmv.training.evaluation import evaluate

DDP = ["trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2", "trainer.precision=32"]


@pytest.fixture(scope="module")
def uneven_dataset(tmp_path_factory):
    """12 scenes, 3 of them in the test split: two ranks test 2 and 1."""
    out = tmp_path_factory.mktemp("ddp") / "data"
    splits = {"train": 0.5, "val": 0.25, "test": 0.25}
    simulate(
        SimSettings(out=out, scenes=12, height_px=32, width_px=32, seed=3, splits=splits),
        workers=1,
        progress=False,
    )
    return out


def _train(*args, cwd):
    cmd = [
        sys.executable,
        "-m",
        "odmv.train",
        *args,
        "data.resolution=32",
        "data.num_workers=0",
        "data.progress=false",
        "widths.odmvnet=4",
        "model.net.blocks=1",
        "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false",
        "trainer.enable_model_summary=false",
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=cwd)


def test_ddp_on_cpu_counts_each_test_scene_once(uneven_dataset, tmp_path):
    run = tmp_path / "run"
    done = _train(*DDP, "data=exr", f"root={uneven_dataset}", f"hydra.run.dir={run}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[:4000] + "\n...\n" + done.stderr[-4000:]
    assert "sync_dist" not in done.stderr and "SyncBatchNorm" not in done.stderr
    assert done.stdout.count("run folder:") == 1  # printed by rank zero only
    with (run / "metrics.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 1  # one row, not one per rank
    with (run / "test_scenes.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == 3
    metrics = json.loads((run / "metrics.json").read_text())
    cfg = compose_config(
        "evaluate",
        [
            f"ckpt_path={run / metrics['best_checkpoint']}",
            f"paths.output_dir={tmp_path / 'eval'}",
            "figures=0",
            "accelerator=cpu",
            "progress=false",
        ],
    )
    single = evaluate(cfg, [])
    for key in ("test/mae_mm", "test/rmse_mm", "test/mae_mm_shadowed", "test/share_shadowed"):
        assert metrics[key] == pytest.approx(single[key], rel=1e-5), key


def test_multirun_refuses_local_ddp(uneven_dataset, tmp_path):
    sweep = tmp_path / "sweep"
    done = _train(
        "-m",
        *DDP,
        "views=1,2",
        "data=exr",
        f"root={uneven_dataset}",
        f"hydra.sweep.dir={sweep}",
        cwd=tmp_path,
    )
    assert done.returncode == 2
    with (sweep / "results.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 and all(r["error"].startswith("trainer=ddp: not with -m") for r in rows)
