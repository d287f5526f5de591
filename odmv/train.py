"""Train a net: ``python -m odmv.train model=odmvnet views=4`` (config: conf/train.yaml).

``resume=RUN`` continues a run, ``adapt=true init_from=RUN root=DATASET`` fine-tunes one on a
user's fringes without labels. After fitting it tests the best checkpoint and writes
``metrics.json`` and ``metrics.csv`` into the run folder; multiruns also collect every job into
``results.csv`` in the sweep folder. The workflow is :mod:`odmv.training.run`'s.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from odmv.cli import JobFailed, rank_zero_print, remove_if_empty, run_app, task_overrides, tool
from odmv.config import app
from odmv.io.runfolder import METRICS
from odmv.training.adaptation import adaptation_lines
from odmv.training.configs import run_config
from odmv.training.run import (
    Metrics,
    adopt_hydra_files,
    check_continued_folder,
    check_launch,
    test_line,
    train,
)
from odmv.training.runlock import check_not_held


@app("train")
def main(cfg: DictConfig) -> Metrics | JobFailed:
    from hydra.core.hydra_config import HydraConfig

    hydra_dir = Path(HydraConfig.get().runtime.output_dir)
    folders = [hydra_dir]  # removed if the run fails and leaves them empty

    def body() -> tuple[DictConfig, dict]:
        check_launch(cfg)
        run_cfg = run_config(cfg, task_overrides())
        folders.append(Path(run_cfg.paths.output_dir))
        check_continued_folder(run_cfg, task_overrides())
        check_not_held(folders[-1])  # before anything is moved into another run's folder
        adopt_hydra_files(hydra_dir, folders[-1])
        return run_cfg, train(run_cfg)

    result = run_app(body, folders)
    if isinstance(result, JobFailed):
        return result
    run_cfg, metrics = result
    out = Path(run_cfg.paths.output_dir)
    if out.resolve() != hydra_dir.resolve():  # paths.output_dir=DIR, or another run continued
        remove_if_empty(hydra_dir)
    rank_zero_print(f"run folder: {out}")
    if "tensorboard" in (run_cfg.get("logger") or {}):
        rank_zero_print(f"  TensorBoard: {tool('tensorboard')} --logdir {out / 'tensorboard'}")
    if metrics and metrics.get("adapted_from") and "test/mae_mm" not in metrics:
        said = [f"{what} {value}" for what, value in adaptation_lines(metrics)]
        rank_zero_print("  test (no ground truth): " + "; ".join(said))
    elif metrics and "test/mae_mm" in metrics:
        rank_zero_print(f"  test: {test_line(metrics)}; every figure in {out / METRICS}")
        rank_zero_print(f"  its page: {tool('python')} -m odmv.view {out}")
    return Metrics(metrics, run_cfg.get("optimized_metric"))


if __name__ == "__main__":
    main()
