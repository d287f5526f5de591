"""Score finished runs on 200 held-out scenes of their own twin (the held-out set).

A mini protocol's test split has 20 scenes, and two of them (a 12.6 mm capacitor whose fringe
order a net gets right or not) move a run's test MAE by about 0.02 mm: as much as the levers
being compared. The held-out set is 200 fresh scenes of the same twin: the same rig, fringes,
renderer and scene mix as the runs' dataset, the next scene seed (for the protocols' seed 0,
seed 1: scene ``i`` is drawn from the seed sequence ``[1, i]``, disjoint from the training
scenes' ``[0, i]``), all labelled test. It is rendered once beside the dataset. A run's best
checkpoint is scored on it as ``python -m odmv.evaluate`` scores; its metrics go to ``heldout.json``
in the run folder (the constant predictor there is the run's own mean training depth).

    python -m odmv.study heldout 'outputs/accuracy/s4-*-seed*' [--threads 2]
"""

from __future__ import annotations

import argparse
import contextlib
import glob
import io
import json
import shutil
from pathlib import Path

import torch

from odmv.config import compose_app, settings_hash
from odmv.io.atomic import write_json
from odmv.io.manifest import MANIFEST
from odmv.io.runfolder import HELDOUT, METRICS, portable, recorded_dataset
from odmv.sim.shifts import Shift
from odmv.sim.writer import SimSettings, simulate
from odmv.study.records import best_checkpoint
from odmv.training.evaluation import evaluate

SCENES = 200


class HeldoutError(ValueError):
    """A one-line error naming the dataset or run at fault."""


def twin_settings(
    source: Path,
    name: str,
    scenes: int,
    seed: int,
    images: str,
    shift: Shift | None = None,
    split: str = "test",
) -> SimSettings:
    """The settings of a twin of dataset ``source``, beside it: its rig, fringes, renderer and
    scene mix, ``scenes`` scenes drawn from ``seed``, all of them in ``split``, under ``shift``
    (None: the nominal twin), in folder ``name-KEY``. KEY hashes everything that sets the
    twin's pixels, so datasets that differ only in their training scenes (randomized or
    shifted) share one twin instead of rendering it again."""
    try:
        m = json.loads((source / MANIFEST).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise HeldoutError(f"{source / MANIFEST}: unreadable ({e})") from None
    sim = dict(m.get("simulation") or {})
    if not sim:
        raise HeldoutError(f"{source}: not rendered by odmv.simulate; it has no twin to draw")
    # a twin is the nominal rig unless a shift is asked: neither the source's shift nor its
    # randomized training scenes carry over (a twin has test scenes only)
    sim.pop("shift", None)
    sim.pop("randomize", None)
    spec = {
        **sim,
        "resolution": [m["image_size"]["height_px"], m["image_size"]["width_px"]],
        "views": m["views"],
        "fringe": m["fringe"],
        "scenes": scenes,
        "seed": seed,
        "images": images,
        "splits": {k: int(k == split) for k in ("train", "val", "test")},
        **({"shift": shift.to_dict()} if shift is not None and not shift.nominal else {}),
    }
    out = source.parent / f"{name}-{settings_hash(spec | {'rig': m['rig']})}"
    return SimSettings.from_dict(spec | {"out": str(out)})


def twin_dataset(source: Path, settings: SimSettings) -> Path:
    """Render (or finish) the twin of ``source`` that ``settings`` (:func:`twin_settings`)
    describe; returns its folder."""
    out = Path(settings.out)
    m = json.loads((source / MANIFEST).read_text())
    if not settings.complete():
        print(f"rendering {out} (once)", flush=True)
        simulate(settings, workers=1, progress=False)
    rendered = json.loads((out / MANIFEST).read_text())

    def sequence(fringe: dict) -> dict:  # what the rig projects (uniform: what is stored)
        return {k: v for k, v in fringe.items() if k != "uniform"}

    if rendered["rig"] != m["rig"] or sequence(rendered["fringe"]) != sequence(m["fringe"]):
        raise HeldoutError(f"{out}: its rig or fringes differ from {source}'s; delete it")
    return out


def heldout_dataset(source: Path, scenes: int = SCENES) -> Path:
    """Render (or finish) the held-out twin of dataset ``source`` (``scenes`` scenes); returns
    its folder."""
    seed = source_seed(source) + 1
    name = f"heldout{scenes}-seed{seed}"
    return twin_dataset(source, twin_settings(source, name, scenes, seed, "training"))


def source_seed(source: Path) -> int:
    """The scene seed dataset ``source`` was rendered from (its manifest's record)."""
    try:
        return int(json.loads((source / MANIFEST).read_text())["simulation"].get("seed", 0))
    except (OSError, json.JSONDecodeError, KeyError) as e:
        raise HeldoutError(f"{source / MANIFEST}: no simulation record ({e})") from None


def evaluate_on(
    run: Path, data: Path, threads: int | None, what: str, extra: tuple[str, ...] = ()
) -> dict:
    """Test metrics of ``run``'s best checkpoint on dataset ``data`` (what ``python -m
    odmv.evaluate`` computes, with the overrides ``extra``; ``what`` names the scoring in
    errors). torch's thread count is ``threads`` while it runs, and restored after."""
    ckpt, _ = best_checkpoint(run)
    if not ckpt.is_file():
        raise HeldoutError(f"{run}: its best checkpoint {ckpt.name} is gone; it cannot be scored")
    scratch = run / f".{what}"
    shutil.rmtree(scratch, ignore_errors=True)
    overrides = [
        f"ckpt_path={ckpt}",
        f"root={data}",
        "figures=0",
        "progress=false",
        *([f"threads={threads}"] if threads else []),
        f"paths.output_dir={scratch}",
        *extra,
    ]
    before = torch.get_num_threads()
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # its progress lines, not the study's
            metrics = evaluate(compose_app("evaluate", overrides), overrides)
    except (ValueError, OSError, RuntimeError) as e:
        raise HeldoutError(f"{run}: {what} scoring failed: {e}") from None
    finally:
        torch.set_num_threads(before)
        shutil.rmtree(scratch, ignore_errors=True)
    return metrics | {"dataset": portable(data)}


def score_heldout(run: Path, threads: int | None = None, scenes: int = SCENES) -> dict:
    """Score ``run``'s best checkpoint on its dataset's held-out set of ``scenes`` scenes
    (rendered on first use) and write the metrics to ``run/heldout.json``; returns them.
    ``threads``: torch's intra-op thread count for the evaluation (None: torch's default)."""
    _, metrics = best_checkpoint(run)
    held = evaluate_on(
        run, heldout_dataset(recorded_dataset(metrics, run), scenes), threads, "heldout"
    )
    write_json(run / HELDOUT, held)
    return held


def main(argv: list[str]) -> None:
    """Score finished runs on their dataset's held-out set (each run's heldout.json, skipped
    where it exists) and print it beside the test split."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="+", help="globs of run folders holding metrics.json")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--scenes", type=int, default=SCENES, help="held-out scenes")
    args = ap.parse_args(argv)
    runs = sorted({Path(r) for g in args.runs for r in glob.glob(g)})
    runs = [r for r in runs if (r / METRICS).is_file()]
    if not runs:
        raise SystemExit(f"error: no finished runs match {args.runs}")
    for run in runs:
        held = (
            json.loads((run / HELDOUT).read_text())
            if (run / HELDOUT).is_file()
            else score_heldout(run, args.threads, args.scenes)
        )
        test = json.loads((run / METRICS).read_text())["test/mae_mm"]
        print(
            f"{run}: held-out MAE {held['test/mae_mm']:.4f} mm (shadowed "
            f"{held['test/mae_mm_shadowed']:.4f}), test split {test:.4f} mm",
            flush=True,
        )
