"""The main job on a fresh machine (``make demo``, or ``python -m odmv.demo [key=value ...]``
with train's overrides): render the quickstart dataset, train the quickstart ODMV-Net on the
CPU with the threads other work leaves free (said at the start; ``threads=N`` chooses), evaluate
it against a constant-depth predictor, and say where the logs and figures are."""

from __future__ import annotations

import sys
import time
from datetime import datetime
from pathlib import Path

from hydra import compose, initialize_config_dir

from odmv.cli import run_app, tool
from odmv.config import CONF_DIR  # (and registers the config resolvers)
from odmv.page.document import page_of
from odmv.training.evaluation import evaluate, report
from odmv.training.pace import free_threads
from odmv.training.run import next_steps, train


def main(argv: list[str]) -> int:
    if argv and argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0
    out = Path("outputs/demo") / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    t0 = time.perf_counter()
    if not any(a.startswith("threads=") for a in argv):
        threads, why = free_threads()
        print(f"threads: {why}", flush=True)
        argv = [*argv, f"threads={threads}"]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(
            "train",
            overrides=["experiment=quickstart", f"paths.output_dir={out}", *argv],
        )
        metrics = train(cfg)
        ecfg = compose(
            "evaluate",
            overrides=[
                f"ckpt_path={metrics['best_checkpoint']}",
                f"paths.output_dir={out / 'evaluation'}",
                f"threads={cfg.threads}" if cfg.get("threads") else "threads=null",
            ],
        )
        em = evaluate(ecfg)
    minutes = (time.perf_counter() - t0) / 60
    ratio = em["constant/mae_mm"] / em["test/mae_mm"]
    print("\n" + report(em))
    print(f"the model's MAE is {ratio:.1f}x smaller than the constant predictor's")
    precision = {"32": "float32"}.get(str(cfg.trainer.precision), cfg.trainer.precision)
    print(f"wall time: {minutes:.1f} min (trained in {precision})")
    print(f"TensorBoard: {tool('tensorboard')} --logdir {out / 'tensorboard'}")
    print(f"figures    : {out / 'evaluation' / 'figures'}")
    print(f"page       : {page_of(out)} (open it in a browser, offline)")
    print("\nwhat to run next, from this run:")
    print("\n".join(f"  {line}" for line in next_steps(out, Path(metrics["best_checkpoint"]))))
    return 0


if __name__ == "__main__":
    # run_app: the apps' quiet output and one-line errors
    sys.exit(run_app(lambda: main(sys.argv[1:])))
