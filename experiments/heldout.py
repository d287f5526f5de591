"""Score finished runs on a larger held-out set: 200 fresh scenes of the runs' own twin
(odmv.heldout, which the reproduction runs for every row).

    python experiments/heldout.py 'outputs/accuracy/s4-*-seed*' 'outputs/reproduce/mini/*'

Each run's held-out metrics go to ``heldout.json`` in its folder (skipped where that exists).
The protocol's figures stay the test split's; these are extra evidence for decisions.
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

from odmv.heldout import HELDOUT, score_heldout


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="globs of run folders holding metrics.json")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = p.parse_args(argv)
    runs = sorted({Path(r) for g in args.runs for r in glob.glob(g)})
    runs = [r for r in runs if (r / "metrics.json").is_file()]
    if not runs:
        print(f"no finished runs match {args.runs}", file=sys.stderr)
        return 2
    for run in runs:
        held = (
            json.loads((run / HELDOUT).read_text())
            if (run / HELDOUT).is_file()
            else score_heldout(run, args.threads)
        )
        test = json.loads((run / "metrics.json").read_text())["test/mae_mm"]
        print(
            f"{run}: held-out MAE {held['test/mae_mm']:.4f} mm (shadowed "
            f"{held['test/mae_mm_shadowed']:.4f}), test split {test:.4f} mm",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
