"""MAE and coverage against images captured per projector: the classical method from the one
image a network sees (single-shot Fourier-transform profilometry) to the full sequences, on a
dataset's test split, with networks' runs beside it at one image.

    python -m odmv.study captures DATASET --out DIR [--work DIR] ['LABEL=GLOB' ...]

DATASET must hold the full sequences (images=full). Each capture of
odmv.classical.reconstruct.CAPTURES is scored like a trained run in ``--work`` (default
outputs/captures/<dataset>; kept once scored) and its record (``metrics.json``,
``test_scenes.csv``) copied to ``DIR/runs/<capture>/``; each
``LABEL=GLOB`` adds the run folders it matches as one point at one image per projector, the
mean over their seeds, with their MAE on the pixels the full classical capture reconstructs
where their ``test_predictions.npz`` holds every test scene (a run folder's does; a record's
keeps the figure scenes only). Writes
``DIR/captures.md`` (the table, with the command), ``DIR/captures.csv`` and
``DIR/captures.png`` (MAE on a log scale and coverage against images per projector).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from odmv.classical.reconstruct import CAPTURES
from odmv.data.dataset import DataError
from odmv.io.atomic import write_atomic, write_csv, write_text
from odmv.io.runfolder import METRICS, PREDICTIONS, SCENES_CSV
from odmv.study.classical import classical_row
from odmv.study.records import load_predictions, run_groups

COLUMNS = ("mae_mm", "mae_mm_shadowed", "mae_mm_h8_up", "coverage", "mae_mm_classical_pixels")


def capture_rows(dataset: Path, work: Path, out: Path, resolution) -> list[dict]:
    rows = []
    for capture in CAPTURES:
        folder = work / capture.name
        if (folder / METRICS).is_file() and (folder / PREDICTIONS).is_file():
            m = json.loads((folder / METRICS).read_text())
        else:
            print(f"{capture.label} ...", flush=True)
            m = classical_row(dataset, folder, resolution, capture=capture)
        for name in (METRICS, SCENES_CSV):
            write_text(out / "runs" / capture.name / name, (folder / name).read_text())
        rows.append(
            {"method": f"classical, {capture.label}", "images": capture.images, "seeds": 1}
            | {k: m.get(f"test/{k}", np.nan) for k in COLUMNS}
        )
    rows[-1]["mae_mm_classical_pixels"] = rows[-1]["mae_mm"]
    return rows


def classical_pixels(work: Path) -> dict[str, np.ndarray]:
    """Scene id -> the pixels the full capture reconstructs."""
    ids, pred, _ = load_predictions(work / CAPTURES[-1].name, PREDICTIONS)
    return {str(sid): np.isfinite(p) for sid, p in zip(ids, pred, strict=True)}


def net_rows(groups: list[str], pixels: dict[str, np.ndarray]) -> list[dict]:
    """One row per ``LABEL=GLOB``: the mean over the matched runs' seeds."""
    rows = []
    for arg in groups:
        label, runs = run_groups(arg, METRICS)
        ms = [json.loads((run / METRICS).read_text()) for run in runs]
        row = {"method": label, "images": 1, "seeds": len(ms)}
        for k in COLUMNS:
            values = [m[f"test/{k}"] for m in ms if f"test/{k}" in m]
            row[k] = float(np.mean(values)) if values else (1.0 if k == "coverage" else np.nan)
        on_pixels = [_on_pixels(run, pixels) for run in runs]
        row["mae_mm_classical_pixels"] = (
            float(np.mean(on_pixels)) if all(np.isfinite(on_pixels)) else np.nan
        )
        rows.append(row)
    return rows


def _on_pixels(run: Path, pixels: dict[str, np.ndarray]) -> float:
    if not (run / PREDICTIONS).is_file():
        return np.nan
    ids, pred, depth = load_predictions(run, PREDICTIONS)
    found = {str(s): (p, d) for s, p, d in zip(ids, pred, depth, strict=True)}
    if set(pixels) - set(found):
        return np.nan  # a record: the figure scenes only
    shape = next(iter(pixels.values())).shape
    if found[next(iter(pixels))][0].shape != shape:
        raise DataError(
            f"{run / PREDICTIONS}: its maps are not {shape[0]}x{shape[1]} px as the classical's"
        )
    err = np.concatenate([np.abs(found[s][0] - found[s][1])[m] for s, m in pixels.items()])
    return float(np.nanmean(err))


def table_lines(rows: list[dict]) -> list[str]:
    lines = [
        "| method | images per projector | seeds | MAE (mm) | MAE shadowed (mm) "
        "| MAE above 8 mm (mm) | coverage (%) | MAE on the 24-image classical's pixels (mm) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    # by images, the networks before the classical method at one image
    order = sorted(rows, key=lambda r: (r["images"], r["method"].startswith("classical")))
    for r in order:
        cells = [_mm(r[k]) for k in COLUMNS[:3]]
        lines.append(
            f"| {r['method']} | {r['images']} | {r['seeds']} | {' | '.join(cells)} | "
            f"{100 * r['coverage']:.1f} | {_mm(r['mae_mm_classical_pixels'])} |"
        )
    return lines


def markdown(rows: list[dict], command: str) -> str:
    lines = ["# MAE against images captured per projector", "", f"`{command}`", "", NOTE, ""]
    return "\n".join(lines + table_lines(rows)) + "\n"


def report_section(runs, cells, out: Path) -> list[str]:
    """The reproduction report's section: every classical run of ``runs`` (odmv.study.results)
    by the images it decoded (the full row decodes the last capture's), and each Table II
    net's row (``cells``) at one image; writes ``out/captures.png``. Nothing without captures."""
    classical = [r for r in runs if r.model == "classical"]
    if len(classical) < 2:
        return []
    rows = []
    for r in classical:
        images = r.metrics.get("images_per_projector", CAPTURES[-1].images)
        label = next((c.label for c in CAPTURES if c.images == images), f"{images} images")
        row = {"method": f"classical, {label}", "images": images, "seeds": 1}
        rows.append(row | {k: float(r.metrics.get(f"test/{k}", np.nan)) for k in COLUMNS})
    for c in cells:
        if c.runs and c.row.model != "classical":
            row = {"method": c.label, "images": 1, "seeds": len(c.runs), "coverage": 1.0}
            rows.append(row | {k: c.stat(f"test/{k}")[0] for k in COLUMNS if k != "coverage"})
    figure(out / "captures.png", rows)
    return [
        "### Classical phase shifting against images captured per projector",
        "",
        NOTE + " The networks see one image per projector.",
        "",
        *table_lines(rows),
        "",
        "![MAE and coverage against images captured per projector](captures.png)",
        "",
    ]


NOTE = (
    "Errors on the test split's pixels each method reconstructs (a network answers every "
    "pixel: coverage 100 %); seeds averaged for networks. One frequency: the fringe order is "
    "anchored to the base plane, a period off on regions wholly on parts taller than half a "
    "period (the above-8-mm column)."
)


def _mm(value: float) -> str:
    return f"{value:.4f}" if np.isfinite(value) else "–"


def figure(path: Path, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    classical = sorted(
        (r for r in rows if r["method"].startswith("classical")), key=lambda r: r["images"]
    )
    nets = [r for r in rows if not r["method"].startswith("classical")]
    fig, (ax, cov) = plt.subplots(1, 2, figsize=(10, 4))
    x = [r["images"] for r in classical]
    ax.plot(x, [r["mae_mm"] for r in classical], "o-", color="k", label="classical")
    for r, marker in zip(nets, "s^vD<>ph*", strict=False):
        ax.plot([1], [r["mae_mm"]], marker, label=r["method"], linestyle="none")
    for axis in (ax, cov):
        axis.set_xscale("log")
        axis.set_xlabel("images captured per projector")
        axis.set_xticks(sorted(set(x)), [str(v) for v in sorted(set(x))])
    ax.set_yscale("log")
    ax.set_ylabel("test MAE (mm), on the pixels reconstructed")
    ax.legend(fontsize=7)
    cov.plot(x, [100 * r["coverage"] for r in classical], "o-", color="k")
    cov.set_ylabel("coverage of the valid pixels (%)")
    cov.set_ylim(0, 100)
    fig.suptitle("Classical phase shifting from 1 to 24 images per projector, and networks at 1")
    fig.tight_layout()
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    plt.close(fig)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("runs", nargs="*", metavar="LABEL=GLOB")
    args = parser.parse_intermixed_args(argv)
    work = args.work or Path("outputs") / "captures" / args.dataset.resolve().name
    try:
        rows = capture_rows(args.dataset, work, args.out, args.resolution)
        rows += net_rows(args.runs, classical_pixels(work))
    except (DataError, ValueError) as e:
        raise SystemExit(f"error: {e}") from None
    command = "python -m odmv.study captures " + shlex.join(argv)
    write_text(args.out / "captures.md", markdown(rows, command))
    write_csv(args.out / "captures.csv", rows)
    figure(args.out / "captures.png", rows)
    print(markdown(rows, command), file=sys.stdout)
    return 0
