"""The paper's tables and figures from runs: ``python -m odmv.report runs=[DIR,...] out=DIR``.

``runs`` are run folders (holding ``metrics.json``), sweep folders, or a reproduction's runs
folder; every ``metrics.json`` below them is read. Runs are placed by what they are (model,
views, Table I row), seeds of one row are averaged (mean ± std), and the layout is the paper's:
the view-count table (Sec. III.A), Table I (module ablation, S = 4) and Table II (models). A row
without a finished run is printed as missing, never filled in. Writes ``tables.md``, one CSV per
table, ``runs.csv`` (every run), and PNG figures: Fig. 6 (inputs, ground truth, every Table II
model's prediction and |error| on one mm scale, for the same test scenes), Fig. 7 (scanline
profiles of all models on one plot) and a bar chart per table; and ``page.html``, the same
results as one offline page to turn in 3D (odmv.page; ``python -m odmv.view`` writes it again).
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from odmv.cli import run_app
from odmv.config import app
from odmv.page.document import page_of
from odmv.study.report import write_report


@app("report")
def main(cfg: DictConfig) -> None:
    runs = [cfg.runs] if isinstance(cfg.runs, str) else list(cfg.runs)
    path = run_app(
        lambda: write_report(
            [Path(p) for p in runs], Path(cfg.out), cfg.protocol, cfg.figures, cfg.error_scale_mm
        )
    )
    print(f"report: {path}")
    page = run_app(lambda: page_of(Path(cfg.out)))
    print(f"page  : {page} (open it in a browser, offline)")


if __name__ == "__main__":
    main()
