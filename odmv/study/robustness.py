"""Score finished runs and the classical method on shifted twins of their dataset.

    python -m odmv.study robustness RUN [RUN ...] [--shifts gamma:1.5 gamma:2.2 ...]
        [--missing right down left up] [--scenes 100] [--classical] [--threads 2] [--out DIR]

Each shift (odmv.sim.shifts, ``NAME:STRENGTH``) renders once, beside the runs' dataset, a
test-only twin of it under that shift: its rig, fringes, renderer and scene mix, ``scenes``
scenes from the scene seed after the held-out set's (the dataset's seed + 2: drawn from
neither the training data nor the held-out set), with the nominal calibration in its manifest.
The nominal twin of the same scenes is the baseline every ratio is taken against. Each run's
best checkpoint is scored on every set (``robustness.json`` in the run folder, one entry per
set, kept: a later call scores only what is missing), the classical method (phase shifting with
the nominal calibration) too with ``--classical``, and ``--out`` gets ``robustness.md``,
``robustness.csv`` and ``robustness.png``: MAE per model and set, and its ratio to the model's
nominal MAE.

A run trained with view dropout is also scored with each view of ``--missing`` declared
missing (``missing:VIEW``: the nominal twin, that view's images withheld and the net told so),
which a dead projector becomes once the user knows it; the report then compares it with the
same net trained without dropout (all views present) and with the net trained on three views
(its view count's ``S=3`` row; by the rig's quarter-turn symmetry it stands for any one
missing).
"""

from __future__ import annotations

import argparse
import csv
import functools
import glob
import json
import time
from pathlib import Path

import matplotlib
import numpy as np
from omegaconf import OmegaConf

from odmv.config import display_name
from odmv.io.atomic import write_atomic, write_csv, write_json, write_text
from odmv.io.runfolder import METRICS, ROBUSTNESS, recorded_dataset
from odmv.rig import VIEW_NAMES
from odmv.sim.shifts import KINDS, NOMINAL, NOMINAL_SHIFT, Shift, parse_shift
from odmv.study.heldout import evaluate_on, source_seed, twin_dataset, twin_settings

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

SCENES = 100
SEED_OFFSET = 2  # after the training data (+0) and the held-out set (+1)
#: every shift at the two strengths its entry of odmv.sim.shifts.KINDS names: a drift or fault a
#: rig meets, and a larger one
SHIFTS = tuple(
    f"{name}:{x:g}" if isinstance(x, (int, float)) else f"{name}:{x}"
    for name, kind in KINDS.items()
    for x in kind.study
)


def shifted_set(source: Path, shift: Shift, scenes: int = SCENES, classical: bool = True) -> Path:
    """The shifted twin of dataset ``source``, rendered on first use: full sequences where the
    classical method scores it too, else the networks' images only (about 1/25 of the disk;
    their sensor noise is another draw, so a score moves within noise). A full set already
    there serves the networks too."""
    seed = source_seed(source) + SEED_OFFSET
    name = f"robust{scenes}-seed{seed}-{shift.label().replace(':', '_')}"
    full = twin_settings(source, name, scenes, seed, "full", shift)
    if classical or full.complete():
        return twin_dataset(source, full)
    net = twin_settings(source, f"{name}-net", scenes, seed, "training", shift)
    return twin_dataset(source, net)


def score_run(
    run: Path,
    shifts: list[Shift],
    scenes: int = SCENES,
    threads: int | None = None,
    missing: tuple[str, ...] = VIEW_NAMES,
    classical: bool = True,
) -> dict:
    """``run``'s scores on the nominal and every shifted twin of its dataset, and, if it was
    trained with view dropout, on the nominal twin with each of its views in ``missing``
    declared missing; kept in ``run/robustness.json`` (each set scored once; the file grows
    as sets are added)."""
    path = run / ROBUSTNESS
    scores = json.loads(path.read_text()) if path.is_file() else {}
    record = json.loads((run / METRICS).read_text())
    source = recorded_dataset(record, run)
    sets = [(shift.label(), shift, ()) for shift in [NOMINAL_SHIFT, *shifts]]
    if _setting(run, "view_dropout"):
        sets += [
            (f"missing:{v}", NOMINAL_SHIFT, (f"missing=[{v}]",))
            for v in missing
            if v in (record.get("views") or [])
        ]
    todo = [s for s in sets if not (s[0] in scores and scores[s[0]].get("scenes") == scenes)]
    t0 = time.perf_counter()
    for k, (label, shift, extra) in enumerate(todo):
        print(f"{run.name}: set {k + 1} of {len(todo)}, {label}", flush=True)
        data = shifted_set(source, shift, scenes, classical)
        metrics = evaluate_on(run, data, threads, "robustness", extra)
        scores[label] = {k: v for k, v in metrics.items() if k.startswith("test/")} | {
            "scenes": scenes,
            "dataset": metrics["dataset"],
        }
        write_json(path, scores)
        left = (time.perf_counter() - t0) / (k + 1) * (len(todo) - k - 1)
        print(
            f"{run.name} {label}: MAE {metrics['test/mae_mm']:.4f} mm (about {left / 60:.0f} min "
            "left for this run)",
            flush=True,
        )
    return scores


def plan(source: Path, shifts: list[Shift], scenes: int, runs: int, classical: bool) -> str:
    """What the study will do before it starts: the sets it renders (full sequences where the
    classical method scores them too), their disk at most, and how many runs it scores."""
    from odmv.io.manifest import load_manifest
    from odmv.sim.writer import SimSettings, human_size, scene_bytes_bound

    m = load_manifest(source)
    settings = SimSettings(
        out=source,
        scenes=scenes,
        height_px=m.height_px,
        width_px=m.width_px,
        images="full" if classical else "training",
        views=tuple(m.views),
        fringe=m.fringe,
    )
    sets = 1 + len(shifts)
    need = human_size(scene_bytes_bound(settings) * scenes * sets)
    return (
        f"robustness: {sets} sets of {scenes} scenes at {m.height_px}x{m.width_px} px (the "
        f"nominal twin and {len(shifts)} shifts), rendered once beside {source} (about {need}; "
        f"sets already there are reused), each scored with {runs} run(s)"
        + (
            " and the classical method"
            if classical
            else " (the networks' images only; --classical renders full sequences)"
        )
        + "; a line per set says what is left"
    )


def score_classical(
    source: Path, shifts: list[Shift], scenes: int = SCENES, resolution=None
) -> dict:
    """The classical method's scores (nominal calibration) on the same sets."""
    from odmv.study.classical import classical_row

    scores = {}
    for shift in [NOMINAL_SHIFT, *shifts]:
        data = shifted_set(source, shift, scenes)
        out = data / "classical"
        if (out / METRICS).is_file():
            m = json.loads((out / METRICS).read_text())
        else:
            m = classical_row(data, out, resolution=resolution)
        scores[shift.label()] = {k: v for k, v in m.items() if k.startswith("test/")}
    return scores


def _dataset(run: Path) -> Path:
    return recorded_dataset(json.loads((run / METRICS).read_text()), run)


def _label(run: Path, metrics: dict) -> str:
    """The row a run belongs to: its net, view count and width, and the training settings
    that make a robustness row of their own (a randomized twin, view dropout, a fine-tune of
    another run)."""
    views = len(metrics.get("views") or [])
    odmv = metrics.get("model") == "odmvnet" and metrics.get("width")
    width = f", width {metrics['width']}" if odmv else ""
    name = f"{display_name(str(metrics.get('model')))} (S={views}{width})"
    randomize, dropout = _setting(run, "data.randomize"), _setting(run, "view_dropout")
    if randomize:
        name += f", randomize={randomize}"
    if dropout:
        name += f", view_dropout={dropout}"
    if _setting(run, "init_from"):
        name += ", fine-tuned"
    return name


def _setting(run: Path, key: str):
    """A training setting of ``run`` (its Hydra config; None where unset or unrecorded)."""
    return OmegaConf.select(_config(run), key, default=None)


@functools.cache
def _config(run: Path):
    config = run / ".hydra" / "config.yaml"
    return OmegaConf.load(config) if config.is_file() else OmegaConf.create()


def write_tables(
    rows: dict[str, list[dict]],
    shifts: list[Shift],
    out: Path,
    views: dict[str, list[str]] | None = None,
) -> Path:
    """``robustness.md``, ``robustness.csv`` and ``robustness.png`` of the rows (model label ->
    each seed's scores by set label; ``views``: each row's views, for the view-dropout table)."""
    labels = ["nominal", *[s.label() for s in shifts]]
    shown = len(labels)  # the missing views' sets go to the CSV and the view-dropout table
    labels += [f"missing:{v}" for v in VIEW_NAMES if _any(rows, f"missing:{v}")]
    table, csv_rows = [], []
    for model, seeds in rows.items():
        line = [model, str(len(seeds))]
        nominal = _mean(seeds, "nominal")
        for label in labels:
            mae = _mean(seeds, label)
            ratio = mae / nominal if np.isfinite(mae) and nominal > 0 else np.nan
            cell = "–" if not np.isfinite(mae) else f"{mae:.3f}"
            if label != "nominal" and np.isfinite(ratio):
                cell += f" ({ratio:.2f}x)"
            coverage = _mean(seeds, label, "test/coverage")
            if np.isfinite(coverage):  # the classical method scores what it reconstructs
                cell += f", {100 * coverage:.0f} % covered"
            line.append(cell)
            if np.isfinite(mae):  # a net never told a view is missing has no such row
                csv_rows.append({"model": model, "set": label, "seeds": len(seeds),
                                 "mae_mm": mae, "ratio_to_nominal": ratio})  # fmt: skip
        table.append(line)
    md = [
        "# Robustness: MAE (mm) on shifted twins, and its ratio to the same model's nominal MAE",
        "",
        f"Each set: {_scenes(rows)} scenes; mean over seeds. Shifts: docs/robustness.md. The "
        "classical method's MAE is over the pixels it reconstructs (their share: covered).",
        "",
    ]
    for start in range(0, shown, 8):  # at most eight sets per table: readable widths
        cols = labels[start : min(start + 8, shown)]
        md.append("| model | seeds | " + " | ".join(cols) + " |")
        md.append("|---|---:|" + "---:|" * len(cols))
        md += [
            "| " + " | ".join(r[:2] + r[2 + start : 2 + start + len(cols)]) + " |" for r in table
        ]
        md.append("")
    md += _dropout_table(rows, views or {})
    write_csv(out / "robustness.csv", csv_rows)
    figure(csv_rows, out / "robustness.png")
    return write_text(out / "robustness.md", "\n".join(md) + "\n")


def _any(rows: dict[str, list[dict]], label: str) -> bool:
    return any(label in seed for seeds in rows.values() for seed in seeds)


def _dropout_table(rows: dict[str, list[dict]], views: dict[str, list[str]]) -> list[str]:
    """Each view-dropout row beside its references: the same net trained without dropout
    (every view present) and the three-view net (S=3), under the view it lacks."""
    dropout = [m for m in rows if ", view_dropout=" in m and any("nominal" in s for s in rows[m])]
    if not dropout:
        return []
    md = [
        "## Any set of working projectors",
        "",
        "MAE (mm) on the nominal twin: with every view, with one view declared missing (its "
        "images withheld, the net told), and with one dead but not declared (its images "
        "ambient only). Beside each net trained with view dropout: the same net trained "
        "without it, and the net trained on three views, under the view it does not have.",
        "",
        "| model | seeds | all views | "
        + " | ".join(f"missing {v}" for v in VIEW_NAMES)
        + " | "
        + " | ".join(f"dead {v}" for v in VIEW_NAMES)
        + " |",
        "|---|---:|" + "---:|" * (1 + 2 * len(VIEW_NAMES)),
    ]
    refs = {model: _references(model) for model in dropout}
    shown = dict.fromkeys([*dropout, *(r for pair in refs.values() for r in pair if r in rows)])
    for name in shown:  # each reference once, below the dropout rows
        seeds = rows[name]
        cells = [_cell(seeds, "nominal")]
        lacks = _lacks(views, name)
        for v in VIEW_NAMES:
            cells.append(_cell(seeds, "nominal") if v in lacks else _cell(seeds, f"missing:{v}"))
        cells += [_cell(seeds, f"dead_view:{v}") for v in VIEW_NAMES]
        if lacks:
            cells[0] = "–"
        md.append(f"| {name} | {len(seeds)} | " + " | ".join(cells) + " |")
    verdicts = [line for m in dropout for line in _dropout_verdicts(m, rows, *refs[m], views)]
    return md + [""] + verdicts + ([""] if verdicts else [])


def _references(model: str) -> tuple[str, str]:
    """A view-dropout row's references: the same net without dropout (or fine-tune), and the
    three-view net."""
    base = model.split(", view_dropout=")[0]
    return base, base.replace("S=4", "S=3")


def _dropout_verdicts(model, rows, base, three, views) -> list[str]:
    """One line each: the dropout net with every view against the net without dropout, and
    with its worst missing view against the three-view net."""
    seeds, lines = rows[model], []
    full = _mean(seeds, "nominal")
    if base in rows:
        ref = _mean(rows[base], "nominal")
        lines.append(
            f"- {model}, every view: {full:.4f} mm against {ref:.4f} mm for {base} "
            f"({100 * (full / ref - 1):+.1f} %)."
        )
    gone = {v: _mean(seeds, f"missing:{v}") for v in VIEW_NAMES}
    gone = {v: m for v, m in gone.items() if np.isfinite(m)}
    if three in rows and gone:
        lacks = _lacks(views, three)
        ref = _mean(rows[three], "nominal")
        worst = max(gone, key=gone.get)
        line = f"- {model}, one view missing: "
        if lacks and lacks[0] in gone:
            line += (
                f"{lacks[0]} {gone[lacks[0]]:.4f} mm against {ref:.4f} mm for {three}, which "
                f"lacks it ({100 * (gone[lacks[0]] / ref - 1):+.1f} %); "
            )
        line += (
            f"the worst, {worst}, {gone[worst]:.4f} mm ({100 * (gone[worst] / ref - 1):+.1f} % "
            f"against {three})."
        )
        lines.append(line)
    return lines


def _lacks(views: dict[str, list[str]], row: str) -> list[str]:
    """The rig's views a row's net was not trained on (none where its views are unknown)."""
    return [v for v in VIEW_NAMES if v not in views.get(row, VIEW_NAMES)]


def _cell(seeds: list[dict], label: str) -> str:
    mae = _mean(seeds, label)
    return f"{mae:.3f}" if np.isfinite(mae) else "–"


def _mean(seeds: list[dict], label: str, key: str = "test/mae_mm") -> float:
    v = [s[label][key] for s in seeds if key in s.get(label, {})]
    return float(np.mean(v)) if v else np.nan


def _scenes(rows: dict[str, list[dict]]) -> str:
    found = {s.get("scenes") for seeds in rows.values() for d in seeds for s in d.values()}
    return ", ".join(str(n) for n in sorted(found - {None})) or "?"


#: one colour and marker per series (matplotlib's ten-colour cycle would repeat at the 11th)
STYLES = [
    (plt.get_cmap("tab20")(i), marker)
    for i, marker in zip(range(20), "osD^vP*Xph<>d8H+x|_1", strict=True)
]


def ratio_curves(csv_rows: list[dict]) -> dict[str, dict[str, tuple[list, list[float]]]]:
    """``robustness.csv``'s rows as curves: shift -> model -> (strengths, MAE ratios to
    nominal). Numeric strengths are sorted, with the nominal strength at ratio 1 added; view
    names (dead_view, missing) keep their order. Non-finite ratios are left out."""
    curves: dict[str, dict[str, tuple[list, list[float]]]] = {}
    for r in csv_rows:
        name, _, strength = r["set"].partition(":")
        ratio = float(r["ratio_to_nominal"] or "nan")
        if strength and np.isfinite(ratio):
            curves.setdefault(name, {}).setdefault(r["model"], []).append((strength, ratio))
    out = {}
    for name, models in curves.items():
        nominal = NOMINAL.get(name)
        out[name] = {}
        for model, points in models.items():
            if isinstance(nominal, (int, float)):
                points = sorted([(float(v), q) for v, q in points] + [(float(nominal), 1.0)])
            out[name][model] = ([v for v, _ in points], [q for _, q in points])
    return out


def strength_unit(name: str) -> str:
    """The unit of a shift's strength (``missing``: the view withheld)."""
    return KINDS[name].unit if name in KINDS else "view"


def nets_scale(curves: dict) -> tuple[float, float, dict[str, float]] | None:
    """One shift's curves (model -> (strengths, ratios)): where a method without a net (the
    classical one) moves away from 1 more than four times as far as every net, the y range
    that shows the nets and that method's peak ratio, to be written where its curve runs off
    the top; None where every curve fits one scale."""
    nets = [q for model, (_, ratios) in curves.items() if not model.startswith("classical")
            for q in ratios]  # fmt: skip
    others = {m: max(r) for m, (_, r) in curves.items() if m.startswith("classical")}
    if not nets or not others or max(others.values()) - 1 <= 4 * (max(nets) - 1):
        return None
    lo, hi = min(min(nets), 1.0), max(nets)
    pad = 0.08 * (hi - lo or 0.1)
    return lo - pad, hi + 3 * pad, others


def off_scale_note(others: dict[str, float]) -> str:
    return (
        ", ".join(f"{m.split(' (')[0]} up to {q:.1f}x" for m, q in others.items()) + ", off scale"
    )


def figure(csv_rows: list[dict], path: Path) -> None:
    """One panel per shift: each model's MAE ratio to its nominal MAE against the strength
    (``robustness.csv``'s rows), one colour and marker per model, the legend below the panels."""
    models = list(dict.fromkeys(r["model"] for r in csv_rows))
    curves = ratio_curves(csv_rows)
    names = list(curves)
    cols = min(4, len(names)) or 1
    n_rows = (len(names) + cols - 1) // cols
    fig, axes = plt.subplots(n_rows, cols, figsize=(3.4 * cols, 2.7 * n_rows + 1.2),
                             squeeze=False)  # fmt: skip
    for ax, name in zip(axes.flat, names, strict=False):
        for m, model in enumerate(models):
            if model not in curves[name]:
                continue
            xs, ratios = curves[name][model]
            if isinstance(xs[0], str):  # views: categories
                ax.set_xticks(range(len(xs)), xs)
                xs = list(range(len(xs)))
            colour, marker = STYLES[m % len(STYLES)]
            ax.plot(xs, ratios, color=colour, marker=marker, ms=5, label=model)
        ax.axhline(1.0, color="grey", lw=0.5)
        scale = nets_scale(curves[name])
        if scale:
            ax.set_ylim(scale[0], scale[1])
            ax.text(0.02, 0.97, off_scale_note(scale[2]), transform=ax.transAxes, fontsize=6,
                    va="top")  # fmt: skip
        ax.set_title(name, fontsize=9)
        ax.set_xlabel(strength_unit(name), fontsize=8)
        ax.set_ylabel("MAE / nominal", fontsize=8)
    for ax in list(axes.flat)[len(names) :]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    for ax in list(axes.flat)[1 : len(names)]:  # models only some panels show
        for h, label in zip(*ax.get_legend_handles_labels(), strict=True):
            if label not in labels:
                handles.append(h)
                labels.append(label)
    fig.legend(handles, labels, loc="lower center", ncol=min(4, len(labels)), fontsize=7,
               frameon=False)  # fmt: skip
    rows_of_legend = (len(labels) + 3) // 4
    fig.tight_layout(rect=(0, 0.03 + 0.22 * rows_of_legend / (2.7 * n_rows + 1.2), 1, 1))
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=90, format="png"))
    plt.close(fig)


def replot(folder: Path) -> Path:
    """Redraw ``folder/robustness.png`` from its ``robustness.csv`` (no scoring)."""
    table = Path(folder) / "robustness.csv"
    if not table.is_file():
        raise SystemExit(f"error: {table}: no such file")
    figure(list(csv.DictReader(table.open())), Path(folder) / "robustness.png")
    return Path(folder) / "robustness.png"


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="*", help="globs of finished run folders")
    ap.add_argument(
        "--replot", type=Path, metavar="DIR", help="redraw DIR/robustness.png from its CSV only"
    )
    ap.add_argument("--shifts", nargs="+", default=list(SHIFTS), metavar="NAME:STRENGTH")
    ap.add_argument(
        "--missing",
        nargs="*",
        default=list(VIEW_NAMES),
        metavar="VIEW",
        help="views declared missing, one at a time, for nets trained with view dropout",
    )
    ap.add_argument("--scenes", type=int, default=SCENES)
    ap.add_argument("--classical", action="store_true", help="score the classical method too")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--out", type=Path, default=None, help="folder for the report")
    args = ap.parse_args(argv)
    if args.replot:
        print(f"figure: {replot(args.replot)}")
        return
    shifts = [parse_shift(s) for s in args.shifts]
    runs = sorted(
        {Path(r) for g in args.runs for r in glob.glob(g) if (Path(r) / METRICS).is_file()}
    )
    if not runs:
        raise SystemExit(f"error: no finished runs match {args.runs}")
    unknown = sorted(set(args.missing) - set(VIEW_NAMES))
    if unknown:
        raise SystemExit(f"error: --missing {unknown[0]}: no such view; name {VIEW_NAMES}")
    rows: dict[str, list[dict]] = {}
    views: dict[str, list[str]] = {}
    print(plan(_dataset(runs[0]), shifts, args.scenes, len(runs), args.classical), flush=True)
    for run in runs:
        metrics = json.loads((run / METRICS).read_text())
        label = _label(run, metrics)
        views[label] = list(metrics.get("views") or [])
        rows.setdefault(label, []).append(
            score_run(run, shifts, args.scenes, args.threads, tuple(args.missing), args.classical)
        )
    if args.classical:
        source = _dataset(runs[0])
        rows["classical (nominal calibration)"] = [score_classical(source, shifts, args.scenes)]
    if args.out:
        print(f"report: {write_tables(rows, shifts, args.out, views)}")
