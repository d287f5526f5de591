"""Render a multi-view FPP dataset: ``python -m odmv.simulate out=PATH scenes=N ...``
(``pose=random``: scenes that move, odmv.sim.pose);
``shard=I/N`` renders one shard of it, ``merge=[DIR,...] out=PATH`` joins shards
(odmv.sim.shards).

The workflow is :func:`odmv.data.twin.render_dataset`'s; settings in conf/simulate.yaml.
"""

from __future__ import annotations

import sys

from omegaconf import DictConfig

from odmv.cli import run_app
from odmv.config import app
from odmv.data.twin import render_dataset


@app("simulate")
def main(cfg: DictConfig) -> None:
    code = run_app(lambda: render_dataset(cfg))
    if code:
        sys.exit(code)


if __name__ == "__main__":
    main()
