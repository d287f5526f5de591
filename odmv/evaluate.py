"""Evaluate a checkpoint on its test split: ``python -m odmv.evaluate ckpt_path=PATH``.

Writes ``metrics.json`` (mm, all pixels and pixels shadowed in at least one input view, next to
a constant-depth predictor) and per-sample figures like the paper's Figs. 4-7: input fringes,
ground truth, prediction, absolute error on a fixed mm scale, and a depth profile along a
scanline. The data settings saved in the checkpoint are used; only ``root=PATH`` and
``data.KEY=VALUE`` on the command line change them, and the dataset is read, never rendered.
"""

from __future__ import annotations

from omegaconf import DictConfig

from odmv.cli import run_app, tool
from odmv.config import app
from odmv.training.evaluation import evaluate, report


@app("evaluate")
def main(cfg: DictConfig) -> None:
    metrics = run_app(lambda: evaluate(cfg), cfg.paths.output_dir)
    print(report(metrics))
    print(f"metrics and figures: {cfg.paths.output_dir}")
    print(f"its page: {tool('python')} -m odmv.view {cfg.paths.output_dir}")


if __name__ == "__main__":
    main()
