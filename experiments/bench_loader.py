"""Sample loading speed of the data module, one process (a DataLoader worker's view).

    python experiments/bench_loader.py [--dataset PATH] [--scenes 40] [--resolution 480]

Renders a training-mode dataset into a temporary folder when none is given, then times
plain EXR decoding and the decoded-array cache for 4-view samples.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import torch

from odmv.data import FPPDataModule
from odmv.rig import VIEW_SETS
from odmv.sim.writer import SimSettings, simulate


def _rate(ds, passes: int) -> float:
    t0 = time.perf_counter()
    for _ in range(passes):
        for i in range(len(ds)):
            ds[i]
    return passes * len(ds) / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--scenes", type=int, default=40)
    ap.add_argument("--resolution", type=int, default=480)
    args = ap.parse_args()
    torch.set_num_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="odmv-loader-"))
    try:
        root = args.dataset or tmp / "ds"
        if args.dataset is None:
            simulate(SimSettings(out=root, scenes=args.scenes, images="training"), progress=False)
        common = dict(
            views=VIEW_SETS[4],
            resolution=args.resolution,
            progress=False,
            cache_dir=str(tmp / "cache"),
            split_fractions={"train": 1, "val": 0, "test": 0},
        )
        plain = FPPDataModule(str(root), cache=False, **common)
        plain.setup()
        t0 = time.perf_counter()
        cached = FPPDataModule(str(root), cache=True, **common)
        cached.setup()
        build = time.perf_counter() - t0
        n = len(plain.datasets["train"])
        print(f"{n} samples, 4 views, {args.resolution} px, 1 thread")
        print(f"plain EXR decoding : {_rate(plain.datasets['train'], 2):7.1f} samples/s")
        print(
            f"decoded cache      : {_rate(cached.datasets['train'], 5):7.1f} samples/s "
            f"(built in {build:.1f} s)"
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
