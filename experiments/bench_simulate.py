"""Simulator throughput at the paper's settings; prints figures, asserts nothing.

    python experiments/bench_simulate.py --full-scenes 252 --training-scenes 1000

Renders into a temporary folder (deleted afterwards unless --keep), with every core.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from odmv.io.validation import validate
from odmv.sim.writer import SimSettings, simulate


def _bench(out: Path, mode: str, scenes: int, resolution: int, workers: int | None) -> None:
    s = SimSettings(out=out, scenes=scenes, images=mode, height_px=resolution, width_px=resolution)
    rep = simulate(s, workers=workers, progress=False)
    t0 = time.perf_counter()
    report = validate(out, deep=False)
    t_val = time.perf_counter() - t0
    size_gb = sum(p.stat().st_size for p in out.rglob("*") if p.is_file()) / 1e9
    print(
        f"{mode:8s} {scenes:5d} scenes @ {resolution} px: {rep.seconds:7.1f} s render+write, "
        f"{scenes / rep.seconds:6.2f} scenes/s, {rep.images / rep.seconds:7.1f} images/s, "
        f"{size_gb:6.2f} GB, validate --quick {t_val:5.1f} s ({'ok' if report.ok else 'FAILED'})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full-scenes", type=int, default=252)
    ap.add_argument("--training-scenes", type=int, default=1000)
    ap.add_argument("--resolution", type=int, default=480)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--root", type=Path, default=None, help="where to render (default: a temp dir)")
    ap.add_argument("--keep", action="store_true")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="odmv-bench-", dir=args.root))
    try:
        for mode, n in (("full", args.full_scenes), ("training", args.training_scenes)):
            if n > 0:
                _bench(root / mode, mode, n, args.resolution, args.workers)
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
