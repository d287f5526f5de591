"""Score finished runs on a larger held-out set: 200 fresh scenes of the runs' own twin.

    python experiments/heldout.py 'outputs/accuracy/s4-*-seed*' 'outputs/reproduce/mini/*'
    python experiments/summarize.py 'LABEL=outputs/heldout/accuracy/s4-fw16-seed*' ...

The mini protocol's test split has 20 scenes, and two of them (a 12.6 mm capacitor whose fringe
order a net gets right or not, docs/accuracy.md round 12) move a run's test MAE by about
0.02 mm: as much as the levers being compared. This renders, once, 200 scenes with the same
rig, fringes, renderer and scene mix as the runs' dataset but another scene seed (seed 1: scene
``i`` is drawn from the seed sequence ``[1, i]``, disjoint from the training scenes'
``[0, i]``), all labelled test, and evaluates each run's best checkpoint on it with
``python -m odmv.evaluate`` into ``outputs/heldout/<run's parent folder>/<run>`` (skipped
where that holds metrics.json). The constant predictor there is the runs' own mean training
depth. The protocol's figures stay the test split's; these are extra evidence for decisions.
"""

from __future__ import annotations

import argparse
import glob
import json
import subprocess
import sys
from pathlib import Path

from split_predictions import best_checkpoint  # this folder's sibling script

from odmv.io.manifest import MANIFEST
from odmv.sim.writer import SimSettings, simulate

ROOT = Path(__file__).resolve().parent.parent
SCENES, SEED = 200, 1


def heldout_dataset(source: Path, out: Path) -> Path:
    """Render (or finish) the held-out twin of dataset ``source`` into ``out``."""
    m = json.loads((source / MANIFEST).read_text())
    sim = dict(m["simulation"])
    settings = SimSettings.from_dict(
        {
            **sim,
            "out": str(out),
            "resolution": [m["image_size"]["height_px"], m["image_size"]["width_px"]],
            "views": m["views"],
            "fringe": m["fringe"],
            "scenes": SCENES,
            "seed": SEED,
            "images": "training",
            "splits": {"train": 0, "val": 0, "test": 1},
        }
    )
    if settings.seed == sim.get("seed"):
        raise SystemExit(f"{source}: rendered with seed {SEED}; its held-out set would repeat it")
    if not settings.complete():
        print(f"rendering the held-out set into {out} (once)", flush=True)
        simulate(settings, workers=1, progress=False)
    rendered = json.loads((out / MANIFEST).read_text())
    if rendered["rig"] != m["rig"] or rendered["fringe"] != m["fringe"]:
        raise SystemExit(f"{out}: its rig or fringes differ from {source}'s; delete it")
    return out


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="globs of run folders holding metrics.json")
    args = p.parse_args(argv)
    runs = sorted({Path(r) for g in args.runs for r in glob.glob(g)})
    runs = [r for r in runs if (r / "metrics.json").is_file()]
    if not runs:
        print(f"no finished runs match {args.runs}", file=sys.stderr)
        return 2
    for run in runs:
        ckpt, metrics = best_checkpoint(run)
        source = Path(metrics["dataset"])
        data = heldout_dataset(source, source.parent / f"heldout-{source.name}-seed{SEED}")
        out = ROOT / "outputs" / "heldout" / run.resolve().parent.name / run.name
        if not (out / "metrics.json").is_file():
            subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "odmv.evaluate",
                    f"ckpt_path={ckpt}",
                    f"root={data}",
                    "figures=0",
                    "progress=false",
                    f"hydra.run.dir={out}",
                ],
                check=True,
                cwd=ROOT,
                stdout=subprocess.DEVNULL,
            )
        held = json.loads((out / "metrics.json").read_text())
        print(
            f"{run}: held-out MAE {held['test/mae_mm']:.4f} mm (shadowed "
            f"{held['test/mae_mm_shadowed']:.4f}), test split {metrics['test/mae_mm']:.4f} mm",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
