"""Does a net measure or remember? The prior probe: the run's test scenes moved and tilted.

    python -m odmv.study prior RUN [RUN ...] [--out DIR] [--threads 2] [--no-classical]

Renders the run's test scenes again (the same seeds, parts and noise) with the whole scene
moved along the camera axis, away from the camera, by 1, 3 and 5 mm, and tilted 5 degrees about
the world x axis (``--moves``, ``--tilt``), as twins beside the run's dataset (rendered once,
shared by every run of that dataset). Each run's best checkpoint is scored on every moved
copy and on the originals; so is the classical method (12-step phase shifting, fused over the
projectors), which measures and so is flat by construction. A net that measures keeps its
MAE as the scene moves; a net that recalls where the background was does not.

Per run it writes ``prior.json`` into the run folder (kept with its record): per move the MAE,
interior and edge MAE (mm) and their ratio to the unmoved scenes, and the slope (mm of MAE per
mm moved, a least-squares line through the unmoved and moved MAEs). ``--out`` (default: the
first run's folder) gets the table (``prior.md``) and the figure (``prior.png``) of all runs.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import replace
from pathlib import Path

import matplotlib
import numpy as np

from odmv.config import settings_hash
from odmv.io.atomic import write_json, write_text
from odmv.io.manifest import MANIFEST
from odmv.io.runfolder import METRICS, PRIOR, recorded_dataset
from odmv.study.classical import classical_row
from odmv.study.heldout import HeldoutError, evaluate_on, twin_dataset, twin_settings
from odmv.study.records import run_data
from odmv.training.checkpoint import CheckpointError

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

OFFSETS_MM = (1.0, 3.0, 5.0)
TILT_DEG = 5.0
FIGURES = ("mae_mm", "mae_mm_interior", "mae_mm_edge")


def moves(offsets_mm=OFFSETS_MM, tilt_deg: float = TILT_DEG) -> list[dict]:
    """The probe's moves: each ``{"name", "offset_mm", "tilt_deg": [about x, about y]}``."""
    out = [{"name": "none", "offset_mm": 0.0, "tilt_deg": [0.0, 0.0]}]
    out += [
        {"name": f"{o:g} mm", "offset_mm": float(o), "tilt_deg": [0.0, 0.0]} for o in offsets_mm
    ]
    if tilt_deg:
        out.append(
            {"name": f"tilt {tilt_deg:g} deg", "offset_mm": 0.0, "tilt_deg": [tilt_deg, 0.0]}
        )
    return out


def moved_dataset(source: Path, ids: list[str], move: dict) -> Path:
    """The twin of ``source`` holding its scenes ``ids`` moved by ``move`` (rendered on first
    use, beside ``source``); the full sequences where ``source`` has them (the classical row)."""
    m = json.loads((source / MANIFEST).read_text())
    seed = int(m.get("simulation", {}).get("seed", 0))
    base = twin_settings(source, "prior", int(m["simulation"]["scenes"]), seed, m["images"])
    s = replace(
        base,
        subset=tuple(sorted(int(i) for i in ids)),
        move={"offset_mm": move["offset_mm"], "tilt_deg": list(move["tilt_deg"])},
    )
    key = settings_hash(s.content_key() | {"rig": m["rig"], "fringe": m["fringe"]})
    return twin_dataset(source, replace(s, out=source.parent / f"prior-{key}"))


def _figures(metrics: dict) -> dict[str, float]:
    return {k: float(metrics.get(f"test/{k}", float("nan"))) for k in FIGURES}


def slope(rows: list[dict], key: str = "mae_mm") -> float:
    """mm of MAE per mm moved: the least-squares line through the unmoved and shifted MAEs."""
    pts = [(r["offset_mm"], r[key]) for r in rows if r["tilt_deg"] == [0.0, 0.0]]
    x, y = np.array(pts, float).T
    return float(np.polyfit(x, y, 1)[0]) if len(x) > 1 else float("nan")


def with_ratios(rows: list[dict]) -> list[dict]:
    """Each row with its figures' ratios to the unmoved row's."""
    base = rows[0]
    return [r | {f"ratio_{k}": r[k] / base[k] for k in FIGURES} for r in rows]


def probe_run(run: Path, plan: list[dict], threads: int | None, classical: bool, cache: dict):
    """Score ``run`` (and, once per dataset and move, the classical method) on every move."""
    module, dm = run_data(run, "test")
    ids = list(dm.splits["test"])
    source = recorded_dataset(json.loads((run / METRICS).read_text()), run)
    res = module.hparams.data_cfg.get("resolution")
    net_rows, cl_rows = [], []
    for mv in plan:
        data = source if mv["name"] == "none" else moved_dataset(source, ids, mv)
        print(f"  {run.name}: {mv['name']}", flush=True)
        net = _figures(evaluate_on(run, data, threads, "prior"))
        net_rows.append({**mv, **net})
        if not classical or json.loads((data / MANIFEST).read_text())["images"] != "full":
            continue
        key = (str(data), str(res))
        if key not in cache:
            with tempfile.TemporaryDirectory() as tmp:
                cache[key] = _figures(classical_row(data, tmp, res))
        cl_rows.append({**mv, **cache[key]})
    result = {"run": run.name, "moves": with_ratios(net_rows), "slope_mm_per_mm": slope(net_rows)}
    result["slope_interior_mm_per_mm"] = slope(net_rows, "mae_mm_interior")
    if cl_rows:
        result["classical"] = {
            "moves": with_ratios(cl_rows),
            "slope_mm_per_mm": slope(cl_rows),
            "slope_interior_mm_per_mm": slope(cl_rows, "mae_mm_interior"),
        }
    write_json(run / PRIOR, result)
    return result


def table_lines(results: list[dict]) -> list[str]:
    """The probe's table: per run (and the classical method) the MAE and interior MAE at each
    move, as mm and as a ratio to the unmoved scenes, and the slopes."""
    names = [m["name"] for m in results[0]["moves"]]
    head = ["net", *(f"{n}: MAE (ratio)" for n in names), *(f"{n}: interior" for n in names)]
    head += ["slope (mm/mm)", "interior slope (mm/mm)"]
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    seen_classical = set()
    for r in results:
        rows = [(r["run"], r)]
        cl = r.get("classical")
        if cl and json.dumps(cl, sort_keys=True) not in seen_classical:
            seen_classical.add(json.dumps(cl, sort_keys=True))
            rows.append((f"classical ({r['run']}'s scenes)", cl))
        for label, x in rows:
            cols = [label]
            cols += [f"{m['mae_mm']:.4f} ({m['ratio_mae_mm']:.2f}x)" for m in x["moves"]]
            cols += [
                f"{m['mae_mm_interior']:.4f} ({m['ratio_mae_mm_interior']:.2f}x)"
                for m in x["moves"]
            ]
            cols += [f"{x['slope_mm_per_mm']:+.4f}", f"{x['slope_interior_mm_per_mm']:+.4f}"]
            lines.append("| " + " | ".join(cols) + " |")
    return lines


def figure(path: Path, results: list[dict]) -> None:
    """MAE ratio against the move along the camera axis, per run and the classical method."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, title in (
        (axes[0], "ratio_mae_mm", "all pixels"),
        (axes[1], "ratio_mae_mm_interior", "interior pixels"),
    ):
        drawn = set()
        for r in results:
            series = [(r["run"], r["moves"], "-o")]
            if "classical" in r and "classical" not in drawn:
                drawn.add("classical")
                series.append(("classical", r["classical"]["moves"], "--s"))
            for label, rows, style in series:
                pts = [(m["offset_mm"], m[key]) for m in rows if m["tilt_deg"] == [0.0, 0.0]]
                x, y = np.array(pts).T
                ax.plot(x, y, style, label=label)
        ax.axhline(1.1, color="grey", lw=0.8, ls=":")
        ax.set_xlabel("scene moved away from the camera (mm)")
        ax.set_ylabel("MAE / MAE of the unmoved scenes")
        ax.set_yscale("log")
        ax.set_title(title, fontsize=10)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="finished run folders")
    ap.add_argument("--out", type=Path, default=None, help="where prior.md and prior.png go")
    ap.add_argument("--moves", default="1,3,5", help="offsets along the camera axis (mm)")
    ap.add_argument("--tilt", type=float, default=TILT_DEG, help="tilt about x (deg); 0: none")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--no-classical", action="store_true", help="score the nets only")
    args = ap.parse_args(argv)
    try:
        offsets = [float(x) for x in args.moves.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--moves {args.moves!r}: give offsets in mm, e.g. 1,3,5")
    plan, cache, results = moves(offsets, args.tilt), {}, []
    for run in args.runs:
        if not (run / METRICS).is_file():
            raise SystemExit(f"error: {run}: not a finished run (no {METRICS})")
        try:
            results.append(probe_run(run, plan, args.threads, not args.no_classical, cache))
        except (CheckpointError, HeldoutError) as e:
            raise SystemExit(f"error: {e}") from None
    out = args.out or args.runs[0]
    out.mkdir(parents=True, exist_ok=True)
    lines = table_lines(results)
    write_text(out / "prior.md", "\n".join(lines) + "\n")
    figure(out / "prior.png", results)
    print("\n".join(lines) + f"\n\n{out / 'prior.md'}, {out / 'prior.png'}", flush=True)
    return 0


def prior_section(folders: list[Path]) -> list[str]:
    """The report's section of the probe: the table of the runs in ``folders`` that were
    probed (their ``prior.json``); nothing where none was."""
    results = [json.loads((f / PRIOR).read_text()) for f in folders if (f / PRIOR).is_file()]
    if not results:
        return []
    return [
        "### The prior probe: the test scenes moved away from the camera and tilted",
        "",
        "MAE (mm) with the scene moved by each offset (and tilted), its ratio to the unmoved "
        "scenes, and the slope in mm of MAE per mm moved (`odmv.study prior`). A net that "
        "measures keeps its MAE as the classical method does; one that recalls the background "
        "does not.",
        "",
        *table_lines(results),
        "",
    ]
