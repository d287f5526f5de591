"""The paper's tables and figures from runs: ``python -m odmv.report runs=[DIR,...] out=DIR``.

``runs`` are run folders (holding ``metrics.json``), sweep folders, or a reproduction's runs
folder; every ``metrics.json`` below them is read. Runs are placed by what they are (model,
views, Table I row), seeds of one row are averaged (mean ± std), and the layout is the paper's:
the view-count table (Sec. III.A), Table I (module ablation, S = 4) and Table II (models). A row
without a finished run is printed as missing, never filled in. Writes ``tables.md``, one CSV per
table, ``runs.csv`` (every run), and PNG figures: Fig. 6 (inputs, ground truth, every Table II
model's prediction and |error| on one mm scale, for the same test scenes), Fig. 7 (scanline
profiles of all models on one plot) and a bar chart per table.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import hydra
import matplotlib
import numpy as np
from omegaconf import DictConfig

from odmv.cli import run_app
from odmv.config import CONF_DIR
from odmv.io.atomic import write_csv, write_text
from odmv.io.runfolder import METRICS as METRICS_JSON
from odmv.io.runfolder import PREDICTIONS, SCENES_CSV
from odmv.metrics import subset_suffix
from odmv.study.records import HELDOUT
from odmv.study.tables import TITLES, Row
from odmv.study.tables import tables as declared

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

METRICS = ("mae_mm", "mse_mm2", "rmse_mm")
#: the subsets where the first view (the one of every S = 1 row) has no fringe and another
#: view has, as the report names them (odmv.data.subsets); newer than the others, so older
#: records lack them
FIRST_VIEW = {"first_unlit": "first-unlit", "first_shadowed": "first-shadowed"}
FIGURE_SCENES = 3  # test scenes in Fig. 6 and 7: one per scene family
#: the held-out set's columns (odmv.study.heldout): every pixel, then the subsets as named above
HELDOUT_SUBSETS = {"all": "", "shadowed": "shadowed"} | FIRST_VIEW
SPLITS = {"test": "test split", "heldout": "held-out"}  # where a claim is judged


class ReportError(ValueError):
    """A one-line error naming the folder at fault."""


@dataclass
class Run:
    folder: Path
    metrics: dict

    @property
    def model(self) -> str:
        return self.metrics.get("model", "")

    @property
    def n_views(self) -> int:
        return len(self.metrics.get("views") or [])

    @property
    def width(self) -> int | None:
        return self.metrics.get("width")

    def matches(self, row: Row) -> bool:
        if (self.model, self.n_views) != (row.model, row.views):
            return False
        if row.width is not None and self.width != row.width:
            return False
        return row.ablation is None or self.metrics.get("ablation") == row.ablation


@dataclass
class Cell:
    """One row of a table: its runs and their statistics."""

    row: Row
    runs: list[Run] = field(default_factory=list)

    def values(self, key: str) -> np.ndarray:
        return np.array([float(r.metrics.get(key, np.nan)) for r in self.runs], float)

    def by_seed(self) -> list[Run]:
        """The runs in seed order."""
        return sorted(self.runs, key=lambda r: r.metrics.get("seed", 0))

    def stat(self, key: str) -> tuple[float, float]:
        v = self.values(key)
        v = v[np.isfinite(v)]
        if not len(v):
            return np.nan, np.nan
        return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else np.nan


def find_runs(paths: list[Path]) -> tuple[list[Run], list[Path]]:
    """Finished runs (folders with metrics.json) and unfinished ones (a training log, no
    metrics yet) below ``paths``."""
    runs, pending = [], []
    for p in paths:
        if not p.is_dir():
            raise ReportError(f"{p}: no such folder")
        for folder in sorted({f.parent for f in p.rglob(METRICS_JSON)}):
            try:
                metrics = json.loads((folder / METRICS_JSON).read_text())
            except (OSError, json.JSONDecodeError) as e:
                raise ReportError(f"{folder / METRICS_JSON}: unreadable ({e})") from None
            if "test/mae_mm" not in metrics or "model" not in metrics:
                raise ReportError(f"{folder / METRICS_JSON}: not a test result of odmv.train")
            runs.append(Run(folder, metrics | _heldout(folder)))
        for log in p.rglob("train.log"):
            if not (log.parent / METRICS_JSON).is_file():
                pending.append(log.parent)
    return runs, sorted(set(pending))


def _heldout(folder: Path) -> dict:
    """A run's held-out scores (odmv.study.heldout) as ``heldout/...`` metrics; none where it was
    not scored."""
    path = folder / HELDOUT
    if not path.is_file():
        return {}
    try:
        held = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ReportError(f"{path}: unreadable ({e})") from None
    return {f"heldout/{k[5:]}": v for k, v in held.items() if k.startswith("test/")}


def build_tables(runs: list[Run], protocol: str | None = None) -> dict[str, list[Cell]]:
    """Each table's rows (odmv.study.tables, for ``protocol``) with their runs. A run that a
    row of its own width claims (ODMV-Net at width 24) belongs to that row only; the other rows
    take the protocol's width."""
    rows_of = declared(protocol)
    widths = {row.width for rows in rows_of.values() for row in rows} - {None}

    def belongs(run: Run, row: Row) -> bool:
        return run.matches(row) and (row.width is not None or run.width not in widths)

    return {
        name: [Cell(row, [r for r in runs if belongs(r, row)]) for row in rows]
        for name, rows in rows_of.items()
    }


# ----------------------------------------------------------------------------- formatting
def _fmt(mean: float, std: float, digits: int = 4) -> str:
    if not np.isfinite(mean):
        return "missing"
    return f"{mean:.{digits}f}" + (f" ± {std:.{digits}f}" if np.isfinite(std) else "")


def _subset_cell(c: Cell, key: str) -> str:
    """A statistic of a subset metric that older records may lack: `–` where no run has it,
    and how many seeds have it where only some do."""
    if not c.runs:
        return "missing"
    n = int(np.isfinite(c.values(key)).sum())
    if not n:
        return "–"
    return _fmt(*c.stat(key)) + (f" ({n} of {len(c.runs)} seeds)" if n < len(c.runs) else "")


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
        *[f"held-out MAE{' ' + name if name else ''} (mm)" for name in HELDOUT_SUBSETS.values()],
    ]
    head += ["coverage (%)"] if classical else []
    head += ["parameters", "epochs", "train time (min)", "threads"]
    head += ["paper MAE", "paper MSE", "paper RMSE"]
    lines = [f"### {TITLES[name]}", "", "| " + " | ".join(head) + " |"]
    lines.append("|" + "|".join(["---"] + ["---:"] * (len(head) - 1)) + "|")
    for c in cells:
        cols = [c.row.label, str(len(c.runs)) if c.runs else "–"]
        for sub in ("", "_shadowed"):
            cols += [_fmt(*c.stat(f"test/{m}{sub}")) for m in METRICS]
        cols += [_subset_cell(c, f"test/mae_mm_{k}") for k in FIRST_VIEW]
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
        lines.append(f"| {c.row.label} | {paper if paper else '–'} | " + " | ".join(vals) + " |")
    return lines + [""]


CLAIMS_RULE = (
    "Each claim compares mean MAE over seeds, on the test split and on the held-out set (200 "
    "fresh scenes of the same twin: two scenes of a 20-scene split move a run by 0.02 mm). "
    "difference: how much lower the claimed better row is (negative: it is higher) ± its "
    "standard error over seeds (sqrt(s_a²/n_a + s_b²/n_b); for the subset claims, over the "
    "seeds both rows ran). Verdict on each set: `holds` or `does not hold` when the difference "
    "is more than twice its standard error, else `within seed noise` and which way the means "
    "lean; with two seeds this is a weak test. A claim `holds` only where both sets say so; "
    "where they differ (or the rows have no held-out scores) each set's verdict is given."
)


def _verdict(diff: float, se: float) -> str:
    if not np.isfinite(diff):
        return "missing"
    if not np.isfinite(se):
        return "one seed: no verdict"
    if abs(diff) > 2 * se:
        return "holds" if diff > 0 else "does not hold"
    return f"within seed noise ({'holds' if diff > 0 else 'fails'} in the mean)"


def _both(verdicts: dict[str, str]) -> str:
    """One verdict from the test split's and the held-out set's: `holds` only where both say
    so; where they differ, each is given."""
    test, held = verdicts["test"], verdicts["heldout"]
    if test == held:
        return test
    return "; ".join(f"{SPLITS[k]}: {v}" for k, v in verdicts.items())


def _lower(better: Cell, worse: Cell, split: str = "test") -> tuple[float, float]:
    """How much lower ``better``'s mean MAE is than ``worse``'s on ``split`` (test or
    heldout), and its standard error."""
    a, b = better.values(f"{split}/mae_mm"), worse.values(f"{split}/mae_mm")
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if not len(a) or not len(b):
        return np.nan, np.nan
    diff = float(b.mean() - a.mean())
    if len(a) < 2 or len(b) < 2:
        return diff, np.nan
    return diff, float(np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b)))


def _subset_gain(
    many: Cell, one: Cell, subset: str, split: str = "test"
) -> tuple[float, float, float, float]:
    """The relative MAE gain of ``many`` views over ``one`` on all pixels and on ``subset``'s
    (means over seeds), and how much larger the subset's gain is (mean and standard error over
    the seeds both rows ran with the subset's metric), on ``split`` (test or heldout)."""
    by_seed = {r.metrics.get("seed"): r.metrics for r in one.runs}
    key = f"{split}/mae_mm_{subset}"
    pairs = []
    for r in many.runs:
        base = by_seed.get(r.metrics.get("seed"))
        if base is None or key not in base or key not in r.metrics:
            continue
        g = [1 - r.metrics[k] / base[k] for k in (f"{split}/mae_mm", key)]
        pairs.append(g)
    if not pairs:
        return np.nan, np.nan, np.nan, np.nan
    g = np.array(pairs)
    d = g[:, 1] - g[:, 0]
    se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else np.nan
    return float(g[:, 0].mean()), float(g[:, 1].mean()), float(d.mean()), se


def claims_markdown(tables: dict[str, list[Cell]]) -> list[str]:
    """The paper's claims that the three tables can test, each with our evidence and a
    verdict: more views are better (Sec. III.A), every Table I module improves on the row
    before, ODMV-Net beats each single-view baseline (Table II), and the views' gain is larger
    where a projector is shadowed (self-occluded regions), tested on the shadowed pixels and on
    those the single view leaves unlit (FIRST_VIEW)."""
    lines = [
        "### The paper's claims on this twin",
        "",
        CLAIMS_RULE,
        "",
        "| claim | ours: MAE (mm) | difference | verdict |",
        "|---|---|---:|---|",
    ]

    def compare(claim: str, better: Cell, worse: Cell, note: str = "") -> None:
        diff, se = _lower(better, worse)
        means = f"{better.stat('test/mae_mm')[0]:.4f} vs {worse.stat('test/mae_mm')[0]:.4f}"
        shown = f"{_fmt(diff, se)} mm" if np.isfinite(diff) else "–"
        held = _lower(better, worse, "heldout")
        if np.isfinite(held[0]):
            a, b = better.stat("heldout/mae_mm")[0], worse.stat("heldout/mae_mm")[0]
            means += f"; held-out {a:.4f} vs {b:.4f}"
            shown += f"; held-out {_fmt(*held)} mm"
        verdict = _both({"test": _verdict(diff, se), "heldout": _verdict(*held)})
        lines.append(f"| {claim} | {means}{note} | {shown} | {verdict} |")

    views, table1 = tables["views"], tables["table1"]
    for fewer, more in zip(views, views[1:], strict=False):
        compare(f"{more.row.label} below {fewer.row.label}", more, fewer)
    for before, after in zip(table1, table1[1:], strict=False):
        compare(f"{after.row.label} below {before.row.label}", after, before)
    ours = next(c for c in tables["table2"] if c.row.model == "odmvnet")
    for c in tables["table2"]:
        paper = c.row.improvement_pct
        if paper is None:
            continue
        m, b = ours.stat("test/mae_mm")[0], c.stat("test/mae_mm")[0]
        ours_pct = f"{100 * (b - m) / b:.1f} %" if np.isfinite(m) and np.isfinite(b) else "–"
        compare(
            f"{ours.row.label} below {c.row.label}",
            ours,
            c,
            f" (reduction {ours_pct}; paper {paper} %)",
        )
    for subset, name in ({"shadowed": "shadowed"} | FIRST_VIEW).items():
        gains, shown, verdicts = [], [], {}
        for split in SPLITS:
            g_all, g_sub, d, se = _subset_gain(views[-1], views[0], subset, split)
            verdicts[split] = _verdict(d, se)
            if split != "test" and not np.isfinite(d):
                continue  # no held-out scores: the test split's figures alone
            at = "" if split == "test" else "held-out "
            gains.append(
                f"{at}gain {100 * g_all:.1f} % on all, {100 * g_sub:.1f} % on {name} pixels"
                if np.isfinite(d)
                else "–"
            )
            shown.append(f"{at}{100 * d:+.1f} ± {100 * se:.1f} points" if np.isfinite(se) else "–")
        claim = f"{views[-1].row.label} gains more over {views[0].row.label} on {name} pixels"
        lines.append(f"| {claim} | {'; '.join(gains)} | {'; '.join(shown)} | {_both(verdicts)} |")
    return lines + [""]


def table_csv(path: Path, cells: list[Cell]) -> None:
    subsets = ("", "_shadowed", "_unlit", *(f"_{k}" for k in FIRST_VIEW))
    keys = [f"test/{m}{s}" for s in subsets for m in METRICS]
    keys += ["test/coverage"] + [f"test/share{s}" for s in subsets[1:]]
    rows = []
    for c in cells:
        r = {"row": c.row.label, "model": c.row.model, "views": c.row.views}
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
def _relative(path: Path) -> str:
    """A path relative to the working directory where it lies below it (portable reports)."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


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


# ----------------------------------------------------------------------------- figures
def bar_chart(path: Path, name: str, cells: list[Cell]) -> None:
    labels = [c.row.label for c in cells]
    x = np.arange(len(cells))
    fig, ax = plt.subplots(figsize=(max(6, 1.3 * len(cells)), 4))
    for k, (sub, colour, text) in enumerate(
        (("", "tab:blue", "all pixels"), ("_shadowed", "tab:orange", "shadowed pixels"))
    ):
        stats = [c.stat(f"test/mae_mm{sub}") for c in cells]
        means = [s[0] if np.isfinite(s[0]) else 0 for s in stats]
        errs = [s[1] if np.isfinite(s[1]) else 0 for s in stats]
        ax.bar(x + (k - 0.5) * 0.38, means, 0.38, yerr=errs, color=colour, label=text, capsize=3)
    for i, c in enumerate(cells):
        if not c.runs:
            ax.text(i, 0, "missing", ha="center", va="bottom", rotation=90, fontsize=8)
    ax.set_xticks(x, labels, rotation=25, ha="right", fontsize=8)
    ax.set_ylabel("test MAE (mm), mean ± std over seeds")
    ax.set_title(TITLES[name], fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _predictions(run: Run) -> dict[str, np.ndarray] | None:
    path = run.folder / PREDICTIONS
    if not path.is_file():
        return None
    with np.load(path) as z:
        return {
            sid: (p, g)
            for sid, p, g in zip(z["scene_id"], z["pred_mm"], z["depth_mm"], strict=True)
        }


def _fringes(dataset: str, sid: str, shape: tuple[int, int]) -> tuple[list[str], np.ndarray] | None:
    """Every view's input fringe of one scene, from the dataset (None if it is not there)."""
    from odmv.data.dataset import DataError, check_spec, load_scene
    from odmv.io.manifest import ManifestError, load_manifest

    try:
        m = load_manifest(dataset)
        spec = check_spec(m, m.views, list(shape), None, None)
        return list(m.views), load_scene(m, sid, spec)["fringes"]
    except (DataError, ManifestError, OSError, ValueError):
        return None


def pick_scenes(run: Run, count: int) -> list[str]:
    """Test scenes for the figures: one per family (the one with the most shadowed pixels)."""
    path = run.folder / SCENES_CSV
    if not path.is_file():
        return []
    rows = list(csv.DictReader(path.open()))
    best: dict[str, tuple[float, str]] = {}
    for r in rows:
        share = float(r.get("pixels_shadowed") or 0)
        if share >= best.get(r["family"], (-1.0, ""))[0]:
            best[r["family"]] = (share, r["scene"])
    return [sid for _, sid in sorted(best.values(), reverse=True)][:count]


def comparison_figures(
    out: Path, cells: list[Cell], count: int, error_scale_mm: float
) -> list[str]:
    """Fig. 6 and Fig. 7 for the Table II models (of each row the lowest seed whose predictions
    are on disk; the scenes are picked from an ODMV-Net run's per-scene file where there is one,
    and every run of one test split picks the same ones)."""
    preds = []
    for c in cells:
        runs = c.by_seed()
        p = next((p for p in map(_predictions, runs) if p), None)
        if p:
            preds.append((c.row.label, p))
    if not preds:
        return []
    listed = [r for c in cells for r in c.runs if (r.folder / SCENES_CSV).is_file()]
    if not listed:
        return []
    ref_run = next((r for r in listed if r.model == "odmvnet"), listed[0])
    written = []
    for sid in pick_scenes(ref_run, count):
        if not all(sid in p for _, p in preds):
            continue
        gt = preds[0][1][sid][1]
        lo, hi = float(np.nanmin(gt)), float(np.nanmax(gt))
        n = len(preds)
        inputs = _fringes(ref_run.metrics.get("dataset", ""), sid, gt.shape)
        cols = max(n, 5)
        fig, axes = plt.subplots(3, cols, figsize=(2.6 * cols, 8), squeeze=False)
        for ax in axes.flat:
            ax.set_xticks([])
            ax.set_yticks([])
        if inputs:
            for k, (v, img) in enumerate(zip(*inputs, strict=True)):
                axes[0, k].imshow(img, cmap="gray")
                axes[0, k].set_title(f"input {k + 1}: {v}", fontsize=8)
        im = axes[0, 4].imshow(gt, cmap="viridis_r", vmin=lo, vmax=hi)
        axes[0, 4].set_title("ground truth (mm)", fontsize=8)
        fig.colorbar(im, ax=axes[0, 4], fraction=0.046)
        for k, (label, p) in enumerate(preds):
            pred = p[sid][0]
            axes[1, k].imshow(pred, cmap="viridis_r", vmin=lo, vmax=hi)
            axes[1, k].set_title(label, fontsize=7)
            err = np.abs(pred - gt)
            im = axes[2, k].imshow(err, cmap="inferno", vmin=0, vmax=error_scale_mm)
            axes[2, k].set_title(f"|error|, MAE {np.nanmean(err):.3f} mm", fontsize=7)
        fig.colorbar(im, ax=axes[2, n - 1], fraction=0.046, label="|error| (mm)")
        unused = list(axes[0, len(inputs[0]) if inputs else 0 : 4]) + list(axes[0, 5:])
        for ax in unused + list(axes[1:, n:].flat):
            ax.axis("off")
        fig.suptitle(f"Fig. 6 layout: test scene {sid} (|error| on a 0-{error_scale_mm} mm scale)")
        fig.tight_layout()
        name = f"fig6_scene{sid}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        written.append(name)
        # Fig. 7: the row through the most shadowed region is where models differ
        row = gt.shape[0] // 2
        fig, ax = plt.subplots(figsize=(8, 4))
        x = np.arange(gt.shape[1])
        ax.plot(x, gt[row], "k-", lw=2, label="ground truth")
        for label, p in preds:
            ax.plot(x, p[sid][0][row], lw=1, label=label)
        ax.invert_yaxis()
        ax.set_xlabel("column (px)")
        ax.set_ylabel("depth (mm)")
        ax.set_title(f"Fig. 7 layout: profile of scene {sid}, row {row}")
        ax.legend(fontsize=7)
        fig.tight_layout()
        name = f"fig7_scene{sid}.png"
        fig.savefig(out / name, dpi=90)
        plt.close(fig)
        written.append(name)
    return written


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
    tables = build_tables(runs, protocol)
    seconds = sum(float(r.metrics.get("train_seconds", 0)) for r in runs)
    lines = [
        "# odmv reproduction report",
        "",
        f"- protocol: {protocol or 'not given'}",
        f"- dataset: {_dataset_line(runs)}",
        f"- commit: {_recorded(runs, 'commit')}",
        f"- machine: {_recorded(runs, 'machine')}",
        f"- trained: {_dates(runs)}",
        f"- runs: {len(runs)} finished ({seconds / 60:.1f} min of training), {len(pending)} "
        "unfinished",
        "",
        "Metrics are over the test split in mm on depth (MSE in mm², which the paper prints as "
        "mm); mean ± std over seeds (std where a row has two or more). `shadowed`: pixels inside "
        "some projector's footprint but unlit by a projector that covers them, from the "
        "dataset's ground truth of all four projectors, so every model is scored on the same "
        "pixels. `first-unlit`: pixels the first projector (right, the one view of every S = 1 "
        "row) leaves unlit and another lights, where only more views add fringes; most lie "
        "outside its footprint, a band of the field. `first-shadowed`: those inside its "
        "footprint, hidden by occlusion. `–`: the row's records predate those two. held-out: the "
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
    lines += claims_markdown(tables)
    shares = []  # properties of the test split, alike in every run that has them
    for k, name in ({"shadowed": "shadowed", "unlit": "unlit"} | FIRST_VIEW).items():
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
        lines += [f"- `{_relative(p)}`" for p in pending]
        lines.append("")
    lines += ["### Every run", "", "See `runs.csv` (one line per run and seed)."]
    write_csv(
        out / "runs.csv",
        [
            {
                "folder": _relative(r.folder),
                **{k: v for k, v in r.metrics.items() if not isinstance(v, (list, dict))},
                "views": "+".join(r.metrics.get("views") or []),
                **{
                    k: _relative(Path(r.metrics[k]))
                    for k in ("best_checkpoint", "dataset")
                    if r.metrics.get(k)
                },
            }
            for r in runs
        ],
    )
    return write_text(out / "tables.md", "\n".join(lines) + "\n")


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="report")
def main(cfg: DictConfig) -> None:
    runs = [cfg.runs] if isinstance(cfg.runs, str) else list(cfg.runs)
    path = run_app(
        lambda: write_report(
            [Path(p) for p in runs], Path(cfg.out), cfg.protocol, cfg.figures, cfg.error_scale_mm
        )
    )
    print(f"report: {path}")


if __name__ == "__main__":
    main()
