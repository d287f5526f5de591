"""The held-out set of a run's dataset, and a run scored on it.

A mini protocol's test split has 20 scenes, and two of them (a 12.6 mm capacitor whose fringe
order a net gets right or not) move a run's test MAE by about 0.02 mm: as much as the levers
being compared. The held-out set is 200 fresh scenes of the same twin: the same rig, fringes,
renderer and scene mix as the runs' dataset, the next scene seed (for the protocols' seed 0,
seed 1: scene ``i`` is drawn from the seed sequence ``[1, i]``, disjoint from the training
scenes' ``[0, i]``), all labelled test. It is rendered once beside the dataset. A run's best
checkpoint is scored on it with ``python -m odmv.evaluate``; its metrics go to ``heldout.json``
in the run folder (the constant predictor there is the run's own mean training depth).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

from odmv.io.atomic import write_json
from odmv.io.manifest import MANIFEST
from odmv.sim.writer import SimSettings, simulate

SCENES = 200
HELDOUT = "heldout.json"  # a run's held-out metrics, beside its metrics.json


class HeldoutError(ValueError):
    """A one-line error naming the dataset or run at fault."""


def heldout_dataset(source: Path, scenes: int = SCENES) -> Path:
    """Render (or finish) the held-out twin of dataset ``source`` (``scenes`` scenes); returns
    its folder."""
    try:
        m = json.loads((source / MANIFEST).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise HeldoutError(f"{source / MANIFEST}: unreadable ({e})") from None
    sim = dict(m.get("simulation") or {})
    if not sim:
        raise HeldoutError(f"{source}: not rendered by odmv.simulate; it has no held-out twin")
    seed = int(sim.get("seed", 0)) + 1
    out = source.parent / f"heldout{scenes}-{source.name}-seed{seed}"
    settings = SimSettings.from_dict(
        {
            **sim,
            "out": str(out),
            "resolution": [m["image_size"]["height_px"], m["image_size"]["width_px"]],
            "views": m["views"],
            "fringe": m["fringe"],
            "scenes": scenes,
            "seed": seed,
            "images": "training",
            "splits": {"train": 0, "val": 0, "test": 1},
        }
    )
    if not settings.complete():
        print(f"rendering the held-out set into {out} (once)", flush=True)
        simulate(settings, workers=1, progress=False)
    rendered = json.loads((out / MANIFEST).read_text())
    if rendered["rig"] != m["rig"] or rendered["fringe"] != m["fringe"]:
        raise HeldoutError(f"{out}: its rig or fringes differ from {source}'s; delete it")
    return out


def best_checkpoint(run: Path) -> tuple[Path, dict]:
    """A finished run's best checkpoint (found beside it where the run folder was moved) and
    its metrics.json."""
    path = run / "metrics.json"
    if not path.is_file():
        raise HeldoutError(f"{run}: no metrics.json (not a finished run)")
    metrics = json.loads(path.read_text())
    ckpt = Path(metrics["best_checkpoint"])
    if not ckpt.is_file():
        ckpt = run / "checkpoints" / ckpt.name  # the run folder was moved
    return ckpt, metrics


def score_heldout(run: Path, threads: int | None = None, scenes: int = SCENES) -> dict:
    """Score ``run``'s best checkpoint on its dataset's held-out set of ``scenes`` scenes
    (rendered on first use) and write the metrics to ``run/heldout.json``; returns them.
    ``threads``: torch's intra-op thread count for the evaluation (None: torch's default)."""
    ckpt, metrics = best_checkpoint(run)
    if not ckpt.is_file():
        raise HeldoutError(f"{run}: its best checkpoint {ckpt.name} is gone; it cannot be scored")
    data = heldout_dataset(Path(metrics["dataset"]), scenes)
    scratch = run / ".heldout"
    shutil.rmtree(scratch, ignore_errors=True)
    cmd = [
        sys.executable,
        "-m",
        "odmv.evaluate",
        f"ckpt_path={ckpt}",
        f"root={data}",
        "figures=0",
        "progress=false",
        *([f"threads={threads}"] if threads else []),
        f"hydra.run.dir={scratch}",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0 or not (scratch / "metrics.json").is_file():
        last = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        raise HeldoutError(f"{run}: held-out scoring failed (exit {proc.returncode}): {last[0]}")
    held = json.loads((scratch / "metrics.json").read_text())
    held["dataset"] = str(data.resolve())
    write_json(run / HELDOUT, held)
    shutil.rmtree(scratch, ignore_errors=True)
    return held
