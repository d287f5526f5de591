"""The paper's three experiments in one command: ``python -m odmv.reproduce protocol=mini``.

Renders the protocol's dataset, trains every row of the three sweeps (conf/sweep/: views,
ablation, models) for each seed, runs the classical reference on the same test scenes, and
writes the report (odmv.report). Every row is one ``python -m odmv.train`` run in its own folder
under ``runs_dir``; a row whose ``metrics.json`` is on disk is not trained again, so an
interrupted reproduction continues where it stopped; ``retrain`` (row-name patterns) trains
finished rows again after a preset changed, each kept until its new run ends. Each finished
row's results (its ``metrics.json``, config, per-scene errors and the predictions of the scenes
the figures show, not its checkpoints) are also kept in ``records`` beside the report, which is
committed with it: a fresh checkout continues the reproduction from them instead of training
those rows again. Rows that are the same configuration in two tables (ODMV-Net at S = 4 is the
last row of all three) are trained once. Seed 0 of every row runs before seed 1, so a partial
reproduction already fills every table. A study runs its own rows the same way (``rows``,
NAME: [override, ...], or ``study=NAME`` from conf/study/), summarized in ``study.md``.
"""

from __future__ import annotations

import sys

from omegaconf import DictConfig

from odmv.cli import run_app
from odmv.config import app
from odmv.study.runner import run_study

#: how a row is trained: the training app, in a process of its own
TRAIN = [sys.executable, "-m", "odmv.train"]


@app("reproduce")
def main(cfg: DictConfig) -> None:
    run_app(lambda: run_study(cfg, TRAIN))


if __name__ == "__main__":
    main()
