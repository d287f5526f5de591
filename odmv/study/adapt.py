"""Label-free adaptation measured on the twin: per shift, the nominal-trained net, adapted
without labels, and fine-tuned with them (the ceiling), on the shifted and the nominal twin.

    python -m odmv.reproduce protocol=mini study=adapt      (conf/study/adapt.yaml)

For each base run (``adapt.bases``: finished runs, with the phase head or not) and each shift
(``adapt.shifts``): a training set of ``adapt.scenes`` scenes of the shifted twin (the scene
seed after the robustness sets': the dataset's seed + 3; all labelled train, a tenth held out
by each fine-tune), then the training app with ``adaptation.supervised=true init_from=RUN
root=SET`` (with the set's depth: the ceiling) and, for each of ``adapt.variants`` (NAME:
train overrides), ``adapt=true init_from=RUN root=SET`` (label-free; a stale calibration is
refused and recorded as such). The base, adapted and supervised nets
are scored on the robustness study's shifted twin (``adapt.test_scenes`` scenes, the dataset's
seed + 2) and the adapted one on the nominal twin as well. Resumable: a finished fine-tune or
score is kept. Writes, in the study's ``out``: ``adapt.md`` (the table: MAE, the share of the
gap closed, (base - adapted) / (base - supervised), and what adapting cost on the nominal
twin), ``adapt.csv``, ``scores.json`` and each fine-tune's record (``runs/NAME``:
metrics.json, config, train.out).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from odmv.io.atomic import write_csv, write_json, write_text
from odmv.io.processes import run_child
from odmv.io.runfolder import METRICS, kept_copy, portable, recorded_dataset
from odmv.sim.shifts import NOMINAL_SHIFT, Shift, parse_shift
from odmv.study.heldout import evaluate_on, source_seed, twin_dataset, twin_settings
from odmv.study.robustness import shifted_set

SCENES = 100
SEED_OFFSET = 3  # after the training data (+0), the held-out set (+1), the robustness sets (+2)
QUIET = ["trainer.enable_progress_bar=false", "data.progress=false"]
KEPT = (METRICS, ".hydra/config.yaml", "train.out")
REFUSED = "refused.txt"  # a fine-tune the calibration check stopped: its one-line reason


def training_set(source: Path, shift: Shift, scenes: int = SCENES, images="training") -> Path:
    """The shifted twin's training scenes (rendered on first use), all labelled train; with
    ``images`` full, the same scenes with every projector's full sequences."""
    seed = source_seed(source) + SEED_OFFSET
    kind = "" if images == "training" else f"-{images}"
    name = f"adapt{scenes}-seed{seed}-{shift.label().replace(':', '_')}{kind}"
    settings = twin_settings(source, name, scenes, seed, images, shift, split="train")
    return twin_dataset(source, settings)


def images_read(settings: list[str]) -> str:
    """The images a variant's adaptation reads: the full sequences where it fits the net to
    their classical reconstruction, else the one image per projector the net sees."""
    return "full" if "adaptation.target=classical" in settings else "training"


def fine_tune(
    train: list[str], base: Path, data: Path, folder: Path, supervised: bool, threads, extra=()
) -> dict | str:
    """Fine-tune ``base`` on ``data`` into ``folder`` with the training app's command
    ``train`` in a clean process (skipped where it finished or was refused), with train
    overrides ``extra``: the run's metrics, or the calibration check's reason."""
    if (folder / METRICS).is_file():
        return json.loads((folder / METRICS).read_text())
    if (folder / REFUSED).is_file():
        return (folder / REFUSED).read_text().strip()
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    cmd = [
        *train, "adapt=true", f"init_from={base.resolve()}",
        f"root={data.resolve()}", f"adaptation.supervised={str(supervised).lower()}",
        *([f"threads={threads}"] if threads else []), *extra, *QUIET, f"hydra.run.dir={folder}",
    ]  # fmt: skip
    with (folder / "train.out").open("w") as log:
        log.write(" ".join(cmd) + "\n")
        log.flush()
        proc = run_child(cmd, log)
    if (folder / METRICS).is_file():
        return json.loads((folder / METRICS).read_text())
    last = (folder / "train.out").read_text().strip().splitlines()[-1]
    if proc.returncode == 2 and "views disagree" in last:
        write_text(folder / REFUSED, last + "\n")
        return last
    raise RuntimeError(f"{folder / 'train.out'}: fine-tune failed (exit {proc.returncode})")


def _score(scores: dict, path: Path, key: str, run: Path, data: Path, threads) -> float:
    """MAE (mm) of ``run`` on ``data``, kept in ``scores`` under ``key`` (scored once)."""
    if key not in scores:
        metrics = evaluate_on(run, data, threads, "adaptation")
        scores[key] = {k: v for k, v in metrics.items() if k.startswith("test/")}
        scores[key]["dataset"] = portable(data)
        write_json(path, scores)
    return scores[key]["test/mae_mm"]


def measure(cfg, runs_dir: Path, out: Path, threads, train: list[str]) -> list[dict]:
    """Every fine-tune and score of the study ``cfg`` (the ``adapt`` settings; resumable);
    returns the table's rows."""
    path = out / "scores.json"
    scores = json.loads(path.read_text()) if path.is_file() else {}
    bases = [Path(b) for b in cfg.bases]
    missing = [str(b) for b in bases if not (b / METRICS).is_file()]
    if missing:
        raise ValueError(f"adapt.bases: {', '.join(missing)}: not a finished run (no {METRICS})")
    extra = list(cfg.get("overrides") or [])
    # each adaptation variant: NAME -> its train overrides (the adapted runs' names)
    variants = {k: list(v or []) for k, v in (cfg.get("variants") or {"adapted": []}).items()}
    rows = []
    for base in bases:
        source = recorded_dataset(json.loads((base / METRICS).read_text()), base)
        nominal = shifted_set(source, NOMINAL_SHIFT, cfg.test_scenes, classical=False)
        base_nominal = _score(scores, path, f"{base.name}|nominal", base, nominal, threads)
        for shift in (parse_shift(s) for s in cfg.shifts):
            label = shift.label()
            test = shifted_set(source, shift, cfg.test_scenes, classical=False)
            data = training_set(source, shift, cfg.scenes)
            base_mm = _score(scores, path, f"{base.name}|{label}", base, test, threads)
            name = f"{base.name}-supervised-{label.replace(':', '_')}"
            print(f"{name}: fine-tuning on {data.name}", flush=True)
            ceiling = fine_tune(train, base, data, runs_dir / name, True, threads, extra)
            _keep(runs_dir / name, out / "runs" / name)
            supervised_mm = _score(scores, path, f"{name}|{label}", runs_dir / name, test, threads)
            for variant, settings in variants.items():
                row = {"base": base.name, "shift": label, "variant": variant}
                row |= {"base_mm": base_mm, "base_nominal_mm": base_nominal}
                row |= {
                    "supervised_mm": supervised_mm,
                    "supervised_seconds": ceiling.get("train_seconds"),
                }
                name = f"{base.name}-{variant}-{label.replace(':', '_')}"
                folder = runs_dir / name
                own = training_set(source, shift, cfg.scenes, images_read([*extra, *settings]))
                print(f"{name}: adapting to {own.name}", flush=True)
                result = fine_tune(train, base, own, folder, False, threads, [*extra, *settings])
                _keep(folder, out / "runs" / name)
                if isinstance(result, str):
                    row["adapted_refused"] = result
                else:
                    row["adapted_mm"] = _score(
                        scores, path, f"{name}|{label}", folder, test, threads
                    )
                    key = f"{name}|nominal"
                    row["adapted_nominal_mm"] = _score(scores, path, key, folder, nominal, threads)
                    row["adapted_seconds"] = result.get("train_seconds")
                    row["view_spread_mm"] = result.get("view_spread_mm")
                rows.append(row)
                print(_line(row), flush=True)
    return rows


def run_adaptation(cfg, runs_dir: Path, out: Path, threads, train: list[str], command: str):
    """The study of ``cfg`` (the ``adapt`` settings), its table written into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    rows = measure(cfg, runs_dir, out, threads, train)
    write_table(rows, out, command)
    print(f"adaptation: {out / 'adapt.md'}", flush=True)
    return out


def _keep(folder: Path, record: Path) -> None:
    """A fine-tune's record: its metrics, config and log (no checkpoints)."""
    for name in (*KEPT, REFUSED):
        if (folder / name).is_file():
            (record / name).parent.mkdir(parents=True, exist_ok=True)
            kept_copy(folder / name, record / name)


def gap_closed(row: dict) -> float | None:
    """(base - adapted) / (base - supervised): 1 where label-free adaptation reaches the
    supervised fine-tune, 0 where it does nothing, below 0 where it harms."""
    if "adapted_mm" not in row or "supervised_mm" not in row:
        return None
    gap = row["base_mm"] - row["supervised_mm"]
    return (row["base_mm"] - row["adapted_mm"]) / gap if gap > 0 else None


def _line(row: dict) -> str:
    adapted = row.get("adapted_mm")
    shown = "refused" if adapted is None else f"{adapted:.4f}"
    return (
        f"{row['base']} {row['shift']} {row['variant']}: base {row['base_mm']:.4f}, adapted "
        f"{shown}, supervised {row['supervised_mm']:.4f} mm"
    )


def _cell(x, fmt="{:.4f}") -> str:
    return "" if x is None else fmt.format(x)


def write_table(rows: list[dict], out: Path, command: str) -> None:
    lines = [
        "# Label-free adaptation on the twin",
        "",
        f"`{command}`",
        "",
        "MAE (mm) on the shifted twin's held-out scenes; gap closed = (base - adapted) / "
        "(base - supervised); nominal: the adapted net on the nominal twin against the base's. "
        "Refused: the calibration check stopped the adaptation (the views disagree).",
        "",
        "| base | shift | variant | base | adapted | supervised | gap closed | nominal: base, "
        "adapted | adapt s |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    csv_rows = []
    for r in rows:
        closed = gap_closed(r)
        adapted = "refused" if "adapted_refused" in r else _cell(r.get("adapted_mm"))
        nominal = f"{r['base_nominal_mm']:.4f}, {_cell(r.get('adapted_nominal_mm')) or '-'}"
        lines.append(
            f"| {r['base']} | {r['shift']} | {r['variant']} | {r['base_mm']:.4f} | {adapted} | "
            f"{_cell(r.get('supervised_mm'))} | {_cell(closed, '{:.0%}')} | {nominal} | "
            f"{_cell(r.get('adapted_seconds'), '{:.0f}')} |"
        )
        csv_rows.append({k: v for k, v in r.items() if not k.endswith("_refused")} |
                        {"gap_closed": closed, "refused": "adapted_refused" in r})  # fmt: skip
    write_text(out / "adapt.md", "\n".join(lines) + "\n")
    write_csv(out / "adapt.csv", csv_rows)
