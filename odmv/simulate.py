"""Render a multi-view FPP dataset: ``python -m odmv.simulate out=PATH scenes=N ...``.

A thin Hydra wrapper around :func:`odmv.sim.writer.simulate`; settings in conf/simulate.yaml.
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig, OmegaConf

from odmv.cli import run_app
from odmv.config import CONF_DIR
from odmv.sim.writer import SimSettings, simulate
from odmv.validate import validate


def settings_from_config(cfg: DictConfig) -> SimSettings:
    """Turn the ``simulate`` config into :class:`SimSettings`."""
    return SimSettings.from_dict(OmegaConf.to_container(cfg, resolve=True))


def run(cfg: DictConfig) -> int:
    """Render, then validate; returns a process exit code."""
    s = settings_from_config(cfg)
    rep = simulate(s, workers=cfg.workers, progress=cfg.progress)
    rate = rep.rendered / rep.seconds if rep.seconds > 0 else float("nan")
    print(
        f"{s.out}: rendered {rep.rendered} scenes ({rep.images} fringe images) in "
        f"{rep.seconds:.1f} s ({rate:.2f} scenes/s), {rep.skipped} already complete"
    )
    if cfg.validate == "off":
        return 0
    report = validate(s.out, deep=cfg.validate == "full")
    if not report.ok:
        print("\n".join(report.problems))
        return 1
    print(report.summary(s.out))
    return 0


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="simulate")
def main(cfg: DictConfig) -> None:
    code = run_app(lambda: run(cfg))
    if code:
        sys.exit(code)


if __name__ == "__main__":
    main()
