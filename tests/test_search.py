"""Sweeps that search: Optuna through Hydra's sweeper over the value train returns, the study
kept in SQLite (a second command continues it), the best trial named in the sweep's summary,
and a failed trial recorded as failed while the search goes on."""

import csv
import subprocess
import sys

import optuna
import pytest
import yaml

TINY = [
    "data=exr",
    "data.resolution=32",
    "data.batch_size=2",
    "data.num_workers=0",
    "data.progress=false",
    "model.net.blocks=1",
    "trainer.max_epochs=1",
    "trainer.limit_train_batches=2",
    "trainer.enable_progress_bar=false",
    "trainer.enable_model_summary=false",
    "log_images=0",
]


def search(cwd, dataset, *overrides, fixed=TINY):
    cmd = [sys.executable, "-m", "odmv.train", "-m", f"root={dataset}", *fixed, *overrides]
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=900)


@pytest.mark.slow
def test_a_two_trial_search_names_its_best_trial_and_continues(tiny_dataset, tmp_path):
    first = search(tmp_path, tiny_dataset, "hparams_search=optuna", "hydra.sweeper.n_trials=2",
                   f"hydra.sweep.dir={tmp_path / 'a'}")  # fmt: skip
    assert first.returncode == 0, first.stderr[-2000:]
    rows = list(csv.DictReader((tmp_path / "a" / "results.csv").open()))
    values = {r["job"]: float(r["val/mae_mm"]) for r in rows}
    best = min(values, key=values.get)
    summary = (tmp_path / "a" / "summary.md").read_text()
    assert f"best: job {best} ({tmp_path / 'a' / best}), val/mae_mm = " in summary
    result = yaml.safe_load((tmp_path / "a" / "optimization_results.yaml").read_text())
    assert result["best_value"] == pytest.approx(values[best])
    # the trials trained other learning rates and widths: rows of their own in the report
    cmd = [sys.executable, "-m", "odmv.report", f"runs=[{tmp_path / 'a'}]", "figures=0",
           f"out={tmp_path / 'report'}"]  # fmt: skip
    report = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert report.returncode == 0, report.stderr[-2000:]
    tables = (tmp_path / "report" / "tables.md").read_text()
    rows = [line.split(" | ") for line in tables.splitlines() if line.startswith("| S=4 (all) [")]
    s4 = [row for row in rows if row[1].isdigit()]  # the view-count table's, not the claims'
    assert len(s4) == 2 and [row[1] for row in s4] == ["1", "1"], tables
    assert "optimizer.lr=" in s4[0][0] and "mixed setups: `S=4 (all)` holds runs of 2" in tables
    assert f"-m odmv.report runs=[{tmp_path / 'a'}]" in first.stdout  # what to run next
    # the study is in multirun/optuna.db: the same search, asked again, goes on from there
    again = search(tmp_path, tiny_dataset, "hparams_search=optuna", "hydra.sweeper.n_trials=1",
                   f"hydra.sweep.dir={tmp_path / 'b'}")  # fmt: skip
    assert again.returncode == 0, again.stderr[-2000:]
    study = optuna.load_study(
        study_name="odmvnet-val/mae_mm", storage=f"sqlite:///{tmp_path / 'multirun' / 'optuna.db'}"
    )
    assert len(study.trials) == 3


@pytest.mark.slow
def test_a_failed_trial_is_recorded_and_the_search_goes_on(tiny_dataset, tmp_path):
    """A user's own search preset (hydra.searchpath) over two input sizes, one of which the
    data refuses (the random sampler at seed 0 asks 33, then 32)."""
    preset = tmp_path / "mine" / "hparams_search" / "sizes.yaml"
    preset.parent.mkdir(parents=True)
    preset.write_text(
        "# @package _global_\n"
        "defaults:\n"
        "  - override /hydra/sweeper: optuna\n"
        "  - override /hydra/sweeper/sampler: random\n"
        "hydra:\n"
        "  sweeper:\n"
        "    storage: null\n"
        "    direction: minimize\n"
        "    n_trials: 2\n"
        "    max_failure_rate: 1.0\n"
        "    sampler:\n"
        "      seed: 0\n"
        "    params:\n"
        "      data.resolution: choice(32, 33)\n"
    )
    fixed = [o for o in TINY if not o.startswith("data.resolution")]  # the search's
    done = search(tmp_path, tiny_dataset, "hparams_search=sizes",
                  f"hydra.searchpath=[file://{tmp_path / 'mine'}]",
                  f"hydra.sweep.dir={tmp_path / 's'}", fixed=fixed)  # fmt: skip
    assert done.returncode == 2  # a job failed: the sweep says so when it ends
    rows = {
        r["data.resolution"]: r for r in csv.DictReader((tmp_path / "s" / "results.csv").open())
    }
    assert rows["32"]["status"] == "ok" and rows["33"]["status"] == "failed"
    assert "data.resolution" in rows["33"]["error"]
    summary = (tmp_path / "s" / "summary.md").read_text()
    assert f"best: job {rows['32']['job']} " in summary and "1 job(s) failed" in summary
