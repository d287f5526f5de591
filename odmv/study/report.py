"""The paper's tables and figures from run records: runs placed by what they are, seeds
averaged, missing rows said, figures drawn (``python -m odmv.report`` writes them; what it
writes: that app's docstring)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from odmv.io.atomic import write_csv, write_text
from odmv.io.runfolder import FAILED, portable
from odmv.study.captures import report_section
from odmv.study.claims import claims_markdown
from odmv.study.figures import FIGURE_SCENES, bar_chart, comparison_figures
from odmv.study.prior import prior_section
from odmv.study.results import (
    EDGES,
    FIRST_VIEW,
    HELDOUT_SUBSETS,
    METRICS,
    Cell,
    ReportError,
    Run,
    build_tables,
    find_runs,
    fmt,
    primary,
)
from odmv.study.tables import TITLES, Row
from odmv.training.metrics import subset_suffix


def _subset_cell(c: Cell, key: str) -> str:
    """A statistic of a subset metric that older records may lack: `–` where no run has it,
    and how many seeds have it where only some do."""
    if not c.runs:
        return "missing"
    n = int(np.isfinite(c.values(key)).sum())
    if not n:
        return "–"
    return fmt(*c.stat(key)) + (f" ({n} of {len(c.runs)} seeds)" if n < len(c.runs) else "")


def _per_seed_cell(c: Cell, key: str) -> str:
    """One field of each seed's record, in seed order ("?" where the record predates it).
    Used for what makes two runs of one row differ although the table gives them one mean:
    the torch thread count (two counts round differently, which moves a run as far as a
    change of seed does) and the epochs trained (a row partly retrained after the preset's
    schedule changed)."""
    return ", ".join(str(r.metrics.get(key, "?")) for r in c.by_seed()) or "–"


def _paper(row: Row, i: int) -> str:
    return f"{row.paper[i]:.4f}" if row.paper else "–"


def table_markdown(name: str, cells: list[Cell]) -> list[str]:
    classical = any(c.row.model == "classical" for c in cells)
    head = [
        "Model",
        "seeds",
        "MAE (mm)",
        "MSE (mm²)",
        "RMSE (mm)",
        "MAE shadowed (mm)",
        "MSE shadowed (mm²)",
        "RMSE shadowed (mm)",
        *[f"MAE {name} (mm)" for name in FIRST_VIEW.values()],
        *[f"MAE {name} (mm)" for name in EDGES.values()],
        *[f"held-out MAE{' ' + name if name else ''} (mm)" for name in HELDOUT_SUBSETS.values()],
    ]
    head += ["coverage (%)"] if classical else []
    head += ["parameters", "epochs", "train time (min)", "threads"]
    head += ["paper MAE", "paper MSE", "paper RMSE"]
    lines = [f"### {TITLES[name]}", "", "| " + " | ".join(head) + " |"]
    lines.append("|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|")
    for c in cells:
        cols = [c.label, str(len(c.runs)) if c.runs else "–"]
        for sub in ("", "_shadowed"):
            cols += [fmt(*c.stat(f"test/{m}{sub}")) for m in METRICS]
        cols += [_subset_cell(c, f"test/mae_mm_{k}") for k in (*FIRST_VIEW, *EDGES)]
        cols += [_subset_cell(c, f"heldout/mae_mm{subset_suffix(k)}") for k in HELDOUT_SUBSETS]
        if classical:
            cov = c.stat("test/coverage")[0]
            cols.append(f"{100 * cov:.1f}" if np.isfinite(cov) else "–")
        params = c.stat("parameters")[0]
        minutes = c.stat("train_seconds")[0] / 60
        cols.append(f"{int(params):,}" if np.isfinite(params) and params > 0 else "–")
        cols.append(_per_seed_cell(c, "epochs"))
        cols.append(f"{minutes:.1f}" if np.isfinite(minutes) and minutes > 0 else "–")
        counts = {r.metrics["threads"] for r in c.runs if "threads" in r.metrics}
        # seeds on other thread counts are not repeats of one configuration: marked
        cols.append(_per_seed_cell(c, "threads") + (" (differ)" if len(counts) > 1 else ""))
        cols += [_paper(c.row, i) for i in range(3)]
        lines.append("| " + " | ".join(cols) + " |")
    return lines + [""]


def improvements_markdown(cells: list[Cell]) -> list[str]:
    """ODMV-Net's relative MAE reduction against each baseline, ours beside the paper's."""
    cells = [c for c in cells if c.primary]
    ours = next(c for c in cells if c.row.model == "odmvnet")
    lines = [
        "### ODMV-Net's MAE reduction against each model (%; positive: ODMV-Net is better)",
        "",
        "| against | paper | ours, all pixels | ours, shadowed pixels | "
        + " | ".join(f"ours, {name} pixels" for name in FIRST_VIEW.values())
        + " |",
        "|---|---:|---:|---:|" + "---:|" * len(FIRST_VIEW),
    ]
    for c in cells:
        if c is ours:
            continue
        vals = []
        for sub in ("", "_shadowed", *(f"_{k}" for k in FIRST_VIEW)):
            base, mine = c.stat(f"test/mae_mm{sub}")[0], ours.stat(f"test/mae_mm{sub}")[0]
            ok = np.isfinite(base) and np.isfinite(mine) and base > 0
            vals.append(f"{100 * (base - mine) / base:.1f}" if ok else "–" if sub else "missing")
        paper = c.row.improvement_pct
        lines.append(f"| {c.label} | {paper if paper else '–'} | " + " | ".join(vals) + " |")
    return lines + [""]


def table_csv(path: Path, cells: list[Cell]) -> None:
    subsets = ("", "_shadowed", "_unlit", *(f"_{k}" for k in (*FIRST_VIEW, *EDGES)))
    keys = [f"test/{m}{s}" for s in subsets for m in METRICS]
    keys += ["test/coverage"] + [f"test/share{s}" for s in subsets[1:]]
    rows = []
    for c in cells:
        r = {"row": c.label, "model": c.row.model, "views": c.row.views}
        r["ablation"] = c.row.ablation or ""
        r["seeds"] = len(c.runs)
        for k in keys + ["parameters", "train_seconds"]:
            mean, std = c.stat(k)
            name = k.removeprefix("test/")
            r[name] = "" if not np.isfinite(mean) else f"{mean:.6g}"
            r[f"{name}_std"] = "" if not np.isfinite(std) else f"{std:.6g}"
        for i, m in enumerate(METRICS):
            r[f"paper_{m}"] = c.row.paper[i] if c.row.paper else ""
        rows.append(r)
    write_csv(path, rows)


# ----------------------------------------------------------------------------- header
def _recorded(runs: list[Run], key: str) -> str:
    """The distinct values of a provenance field over the runs' records, most runs first
    (`unknown` for records that predate it)."""
    counts: dict[str, int] = {}
    for r in runs:
        value = str(r.metrics.get(key) or "unknown")
        counts[value] = counts.get(value, 0) + 1
    ordered = sorted(counts, key=lambda v: (-counts[v], v))
    if len(ordered) == 1:
        return ordered[0]
    return "; ".join(f"{v} ({_runs(counts[v])})" for v in ordered)


def _runs(n: int) -> str:
    return f"{n} run" + ("" if n == 1 else "s")


def _dates(runs: list[Run]) -> str:
    dates = sorted(d for r in runs if (d := r.metrics.get("finished")))
    if not dates:
        return "unknown"
    span = dates[0] if dates[0] == dates[-1] else f"{dates[0]} to {dates[-1]}"
    missing = len(runs) - len(dates)
    return span + (f" ({_runs(missing)} unrecorded)" if missing else "")


def recorded_protocol(runs: list[Run]) -> str | None:
    """The preset every trained run was trained with (``experiment=NAME`` in its recorded
    overrides), or None where they differ or do not say."""
    names = set()
    for r in runs:
        overrides = str(r.metrics.get("overrides", "")).split()
        if not overrides or overrides[0].startswith("resume="):
            continue  # the classical row (no training), or a run continued with its own config
        found = [o.partition("=")[2] for o in overrides if o.startswith("experiment=")]
        names.add(found[-1] if found else None)
    return names.pop() if len(names) == 1 else None


def _protocol_line(given: str | None, protocol: str | None) -> str:
    if given:
        return given
    return f"{protocol} (from the runs' records)" if protocol else "not given"


def _dataset_line(runs: list[Run]) -> str:
    """The runs' datasets by name, with the manifest fingerprints their records hold (never
    read from disk: a rebuilt report says what the records say, wherever it is rebuilt)."""
    found: dict[str, set[str]] = {}
    for r in runs:
        if d := r.metrics.get("dataset"):
            fp = r.metrics.get("dataset_sha1") or "not recorded"
            found.setdefault(Path(d).name, set()).add(fp)
    return ", ".join(
        f"`{name}` (manifest sha1 {', '.join(sorted(fps))})" for name, fps in sorted(found.items())
    ) or ("unknown")


def _mixed_lines(tables: dict[str, list[Cell]]) -> list[str]:
    """Header lines for rows whose runs trained different things, and for rows compared across
    datasets: said, never averaged."""
    lines = []
    for cells in tables.values():
        for c in cells:
            if c.primary and c.variant:
                n = sum(1 for d in cells if d.row == c.row)
                lines.append(
                    f"- mixed setups: `{c.row.label}` holds runs of {n} setups (another dataset "
                    "or setting): each is its own row, named by what sets it apart, and the "
                    "claims use the first"
                )
    used = {r.dataset for cells in primary(tables).values() for c in cells for r in c.runs}
    if len(used) > 1:
        lines.append(
            f"- mixed datasets: the rows come from {len(used)} datasets ({', '.join(sorted(used))})"
            "; rows of different datasets are not like for like"
        )
    return lines


# ----------------------------------------------------------------------------- the report
def write_report(
    folders: list[Path],
    out: Path,
    protocol: str | None = None,
    figures: int = FIGURE_SCENES,
    error_scale_mm: float = 1.0,
) -> Path:
    """Read the runs below ``folders`` and write the report into ``out``; returns tables.md."""
    out = Path(out)
    runs, pending = find_runs([Path(f) for f in folders if Path(f).exists()])
    if not runs:
        raise ReportError(f"{', '.join(map(str, folders))}: no finished run (metrics.json) found")
    out.mkdir(parents=True, exist_ok=True)
    given = protocol
    protocol = protocol or recorded_protocol(runs)
    tables = build_tables(runs, protocol)
    seconds = sum(float(r.metrics.get("train_seconds", 0)) for r in runs)
    lines = [
        "# odmv reproduction report",
        "",
        f"- protocol: {_protocol_line(given, protocol)}",
        f"- dataset: {_dataset_line(runs)}",
        f"- commit: {_recorded(runs, 'commit')}",
        f"- machine: {_recorded(runs, 'machine')}",
        f"- trained: {_dates(runs)}",
        f"- runs: {len(runs)} finished ({seconds / 60:.1f} min of training), {len(pending)} "
        "unfinished",
        *_mixed_lines(tables),
        "",
        "Metrics are over the test split in mm on depth (MSE in mm², which the paper prints as "
        "mm); mean ± std over seeds (std where a row has two or more). `shadowed`: pixels inside "
        "some projector's footprint but unlit by a projector that covers them, from the "
        "dataset's ground truth of all four projectors, so every model is scored on the same "
        "pixels. `first-unlit`: pixels the first projector (right, the one view of every S = 1 "
        "row) leaves unlit and another lights, where only more views add fringes; most lie "
        "outside its footprint, a band of the field. `first-shadowed`: those inside its "
        "footprint, hidden by occlusion. `interior`: pixels 2 px or more from a depth jump over "
        "1 mm; `edge`: the rest, which mix two surfaces. `–`: the row's records predate a "
        "subset. held-out: the "
        "same MAE over 200 fresh scenes of the same twin (odmv.study.heldout; `–`: the row was not "
        "scored there). epochs and "
        "threads: each seed's epochs trained and torch thread count, in seed order (`?`: not "
        "recorded; `(differ)`: the seeds ran on other counts); runs of one configuration with "
        "other thread counts differ as much as seeds do. Paper "
        "columns: the paper's published numbers, for its 480 px protocol; the paper gives no "
        "numbers for S = 1..3. `missing`: no finished run for that row.",
        "",
    ]
    for name, cells in tables.items():
        lines += table_markdown(name, cells)
        table_csv(out / f"{name}.csv", cells)
        bar_chart(out / f"bars_{name}.png", name, cells)
        lines.append(f"![{TITLES[name]}](bars_{name}.png)")
        lines.append("")
    lines += improvements_markdown(tables["table2"])
    lines += report_section(runs, tables["table2"], out)
    lines += claims_markdown(tables)
    lines += prior_section([r.folder for r in runs])
    shares = []  # properties of the test split, alike in every run that has them
    for k, name in ({"shadowed": "shadowed", "unlit": "unlit"} | FIRST_VIEW | EDGES).items():
        v = [r.metrics[f"test/share_{k}"] for r in runs if f"test/share_{k}" in r.metrics]
        shares += [f"{name} {100 * float(np.mean(v)):.1f} %"] if v else []
    if shares:
        lines += [f"Pixel subsets of the test split: {', '.join(shares)} of the valid pixels.", ""]
    names = comparison_figures(out, tables["table2"], figures, error_scale_mm)
    if names:
        lines += ["### Figures (Table II models, of each row its lowest seed with predictions)", ""]
        lines += [f"![{n}]({n})" for n in names]
        lines.append("")
    if pending:
        lines += ["### Unfinished runs (not counted)", ""]
        lines += [
            f"- `{portable(p)}`" + (f" (failed: {FAILED})" if (p / FAILED).is_file() else "")
            for p in pending
        ]
        lines.append("")
    lines += ["### Every run", "", "See `runs.csv` (one line per run and seed)."]
    write_csv(
        out / "runs.csv",
        [
            {
                "folder": portable(r.folder),
                **{k: v for k, v in r.metrics.items() if not isinstance(v, (list, dict))},
                "views": "+".join(r.metrics.get("views") or []),
                **{
                    k: portable(
                        r.folder / r.metrics[k] if k == "best_checkpoint" else Path(r.metrics[k])
                    )
                    for k in ("best_checkpoint", "dataset")
                    if r.metrics.get(k)
                },
            }
            for r in runs
        ],
    )
    return write_text(out / "tables.md", "\n".join(lines) + "\n")
