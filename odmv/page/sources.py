"""What a page shows, read from the folder it is made for: a run folder (``metrics.json`` and
its kept test predictions), a report folder (``tables.md`` and the runs below it or named in its
``runs.csv``), a robustness report (``robustness.csv``) or a predict output (``predict.yaml``).
Fringes, ground truth and the pixel subsets come from the dataset the records name, where it is
on this machine; the page says so where it is not."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from odmv.io.runfolder import METRICS, PREDICTIONS, SCENES_CSV, recorded_dataset
from odmv.study.prior import prior_section
from odmv.study.results import Cell, Run, build_tables, find_runs
from odmv.study.scenes import Scene, scene_inputs
from odmv.training.adaptation import adaptation_lines

SCENES = 3  # scenes a report or run page shows (one per scene family, as Fig. 6)


class PageError(ValueError):
    """One line naming the folder or file at fault."""


@dataclass
class Page:
    title: str
    provenance: list[tuple[str, str]]
    markdown: str = ""  # the folder's own tables (tables.md, robustness.md)
    tables: dict[str, list[Cell]] = field(default_factory=dict)  # report tables, for bar charts
    robustness: list[dict] = field(default_factory=list)  # robustness.csv rows
    scenes: list[Scene] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def read(path: Path) -> Page:
    """The page of a run, report, robustness report or predict output folder."""
    path = Path(path)
    if not path.is_dir():
        raise PageError(f"{path}: no such folder")
    if (path / "robustness.csv").is_file():
        return _robustness(path)
    if (path / "tables.md").is_file():
        return _report(path)
    if (path / "predict.yaml").is_file():
        return _prediction(path)
    if (path / METRICS).is_file():
        return _run(path)
    raise PageError(
        f"{path}: not a run, report or predict output folder (no metrics.json, tables.md, "
        "robustness.csv or predict.yaml)"
    )


# ----------------------------------------------------------------------------- scenes
def _scenes(labelled: list[tuple[str, Run]], dataset: Path | None) -> tuple[list[Scene], list[str]]:
    """The scenes every labelled run kept predictions of (at most SCENES, in the first run's
    order), each with every run's prediction; and notes on what could not be shown."""
    from odmv.study.figures import kept_predictions

    kept = [(label, kept_predictions(run) or {}) for label, run in labelled]
    kept = [(label, k) for label, k in kept if k]
    if not kept:
        return [], ["no run here kept test predictions (test_predictions.npz): no scenes shown"]
    order = list(kept[0][1])
    sids = [s for s in order if all(s in k for _, k in kept)][:SCENES]
    scenes, notes = [], []
    for sid in sids:
        truth = kept[0][1][sid][1]
        found = scene_inputs(dataset, sid, truth.shape) if dataset else None
        scene = found or Scene(sid, truth, {})
        scene.truth_mm = truth
        scene.predictions = {label: k[sid][0] for label, k in kept}
        if found is None:
            scene.note = (
                f"the dataset {dataset} is not on this machine: no input fringes nor pixel subsets"
                if dataset
                else "no dataset recorded: no input fringes nor pixel subsets"
            )
        scenes.append(scene)
    return scenes, notes


def _label_free_scenes(path: Path, dataset: Path | None) -> tuple[list[Scene], list[str]]:
    """An adapted run's kept test scenes (no ground truth): its depth beside the classical
    depth it was fitted to, with the scene's fringes where the dataset is here."""
    from odmv.data.dataset import DataError, check_spec, load_scene
    from odmv.io.manifest import ManifestError, load_manifest

    with np.load(path / PREDICTIONS) as z:
        kept = {k: z[k] for k in z.files}
    try:
        m = load_manifest(dataset) if dataset else None
    except (ManifestError, OSError):
        m = None
    scenes = []
    for k, sid in enumerate(kept["scene_id"][:SCENES]):
        sid = str(sid)
        predictions = {"adapted net": kept["pred_mm"][k]}
        if "classical_mm" in kept:
            predictions["classical reconstruction (its target)"] = kept["classical_mm"][k]
        scene = Scene(sid, None, predictions)
        try:
            shape = list(kept["pred_mm"][k].shape)
            spec = check_spec(m, m.views, shape, None, None, labels=False) if m else None
            fringes = load_scene(m, sid, spec)["fringes"] if m else None
        except (DataError, OSError, ValueError):
            fringes = None
        if fringes is not None:
            scene.views, scene.fringes = list(m.views), dict(zip(m.views, fringes, strict=True))
        else:
            scene.note = f"the dataset {dataset} is not on this machine: no input fringes"
        scenes.append(scene)
    return scenes, []


# ----------------------------------------------------------------------------- provenance
def _values(runs: list[Run], key: str) -> str:
    found = sorted({str(r.metrics[key]) for r in runs if r.metrics.get(key)})
    if not found:
        return "not recorded"
    return (
        found[0]
        if len(found) == 1
        else f"{len(found)} values: {', '.join(found[:4])}" + (", ..." if len(found) > 4 else "")
    )


def _provenance(runs: list[Run]) -> list[tuple[str, str]]:
    finished = sorted(str(r.metrics["finished"]) for r in runs if r.metrics.get("finished"))
    dates = (
        finished[0] if len(set(finished)) == 1 else f"{finished[0]} to {finished[-1]}"
    ) if finished else "not recorded"  # fmt: skip
    prints: dict[str, set] = {}  # name -> fingerprints (records before them have none)
    for r in runs:
        if r.metrics.get("dataset"):
            found = prints.setdefault(Path(r.metrics["dataset"]).name, set())
            found |= {r.metrics["dataset_sha1"]} if r.metrics.get("dataset_sha1") else set()
    datasets = [f"{name} (sha1 {', '.join(sorted(p))})" if p else name
                for name, p in sorted(prints.items())]  # fmt: skip
    return [
        ("commit", _values(runs, "commit")),
        ("dataset", ", ".join(datasets) or "not recorded"),
        ("machine", _values(runs, "machine")),
        ("finished", dates),
        ("runs", str(len(runs))),
    ]


def _dataset(runs: list[Run]) -> Path | None:
    named = [r for r in runs if r.metrics.get("dataset")]
    return recorded_dataset(named[0].metrics, named[0].folder) if named else None


# ----------------------------------------------------------------------------- folder kinds
def _title(kind: str, path: Path) -> str:
    """``odmv KIND NAME``, the parent named too where the folder's name says only the kind
    (``report``, ``robustness``)."""
    path = path.resolve()
    name = path.name if path.name not in kind.split() else f"{path.parent.name}/{path.name}"
    return f"odmv {kind} {name}"


def _run(path: Path) -> Page:
    metrics = json.loads((path / METRICS).read_text())
    run = Run(path, metrics)
    # an evaluation folder inside its run (the demo's): the run's record names the data
    parent = path.parent / METRICS
    named = metrics if metrics.get("dataset") or not parent.is_file() else json.loads(
        parent.read_text()
    )  # fmt: skip
    views = named.get("views") or []
    label = f"{named.get('model', 'run')} (S={len(views)})" if views else path.name
    dataset = _dataset([Run(path, named)])
    label_free = metrics.get("adapted_from") and "test/mae_mm" not in metrics
    scenes, notes = (
        _label_free_scenes(path, dataset) if label_free and (path / PREDICTIONS).is_file()
        else _scenes([(label, run)], dataset)
    )  # fmt: skip
    mae = metrics.get("test/mae_mm")
    prov = _provenance([run])[:-1]
    if mae is not None:
        prov.insert(0, ("test MAE", f"{mae:.4f} mm over the test split"))
    if label_free:
        said = [(f"test: {what}", value) for what, value in adaptation_lines(metrics)]
        prov[:0] = [("adapted from", str(metrics["adapted_from"])), *said]
    if "test/mae_mm_interior" in metrics:
        prov.insert(1, ("interior / edge MAE", (
            f"{metrics['test/mae_mm_interior']:.4f} mm on {metrics['test/share_interior']:.1%} of "
            f"the pixels / {metrics['test/mae_mm_edge']:.4f} mm on the edge band"
        )))  # fmt: skip
    markdown = "\n".join(prior_section([path]))  # the prior probe, where it ran
    return Page(
        f"{_title('run', path)}: {label}", prov, markdown=markdown, scenes=scenes, notes=notes
    )


def _report(path: Path) -> Page:
    runs, _ = find_runs([path])
    if not runs and (path / "runs.csv").is_file():  # a report whose runs live elsewhere
        listed = [Path(r["folder"]) for r in csv.DictReader((path / "runs.csv").open())]
        runs, _ = find_runs([f for f in listed if f.is_dir()])
    page = Page(_title("report", path), [], markdown=(path / "tables.md").read_text())
    if not runs:
        page.notes.append("the runs this report was made from are not on this machine")
        return page
    page.provenance = _provenance(runs)
    page.tables = {k: v for k, v in build_tables(runs).items() if any(c.runs for c in v)}
    labelled = []
    for cell in page.tables.get("table2", []):
        with_predictions = [r for r in cell.by_seed() if (r.folder / PREDICTIONS).is_file()]
        if with_predictions:
            labelled.append((cell.label, with_predictions[0]))
    ordered = _figure_scene_order(runs)
    page.scenes, page.notes = _scenes(labelled, _dataset(runs))
    page.scenes.sort(key=lambda s: ordered.index(s.sid) if s.sid in ordered else len(ordered))
    return page


def _figure_scene_order(runs: list[Run]) -> list[str]:
    """Scenes by the ODMV-Net run's per-scene shadowed share, as the report's figures pick."""
    from odmv.study.figures import pick_scenes

    listed = [r for r in runs if (r.folder / SCENES_CSV).is_file()]
    ref = next((r for r in listed if r.model == "odmvnet"), listed[0] if listed else None)
    return pick_scenes(ref, SCENES) if ref else []


def _robustness(path: Path) -> Page:
    rows = list(csv.DictReader((path / "robustness.csv").open()))
    if not rows or not {"model", "set", "mae_mm", "ratio_to_nominal"} <= set(rows[0]):
        raise PageError(f"{path / 'robustness.csv'}: not a robustness report's table")
    md = path / "robustness.md"
    runs, _ = find_runs([path])
    page = Page(
        _title("robustness report", path),
        _provenance(runs) if runs else [],
        markdown=md.read_text() if md.is_file() else "",
        robustness=rows,
    )
    if not runs:
        page.notes.append("the scored runs' records are not below this folder: no provenance")
    return page


def _prediction(path: Path) -> Page:
    from odmv.io.exr import read_exr
    from odmv.io.manifest import load_manifest

    cfg = OmegaConf.load(path / "predict.yaml")
    folders = [path] if (path / "depth.exr").is_file() else sorted(
        p for p in path.iterdir() if (p / "depth.exr").is_file()
    )  # fmt: skip
    if not folders:
        raise PageError(f"{path}: a predict output without depth.exr (phase only?)")
    source = Path(str(cfg.input))
    method = cfg.get("method", "net")
    label = f"{method}: {Path(str(cfg.ckpt_path)).name}" if method == "net" else method
    about = [("input", str(source)), ("method", label)]
    if method == "net":
        about.append(("checkpoint", str(cfg.get("ckpt_path"))))
    page = Page(_title("prediction", path), about)
    for folder in folders[:SCENES]:
        depth = read_exr(folder / "depth.exr", ["Z"])["Z"].astype(np.float32)
        scene_dir = source if folder == path else source / folder.name
        scene = None
        if (scene_dir.parent.parent / "manifest.json").is_file():  # DATASET/scenes/<id>
            scene = scene_inputs(scene_dir.parent.parent, scene_dir.name, depth.shape)
        if scene is None:
            scene = Scene(folder.name, None, {}, note=_no_truth(scene_dir))
            scene.fringes = _capture_images(scene_dir, depth.shape)
            scene.views = list(scene.fringes)
            if cfg.get("manifest"):
                rig = load_manifest(cfg.manifest).rig
                if rig is not None:
                    cam = rig.camera_at(depth.shape[1], depth.shape[0])
                    scene.mm_per_px = float(np.nanmedian(depth)) / float(cam.K[0, 0])
        scene.predictions = {label: depth}
        page.scenes.append(scene)
    if len(folders) > SCENES:
        page.notes.append(f"{len(folders)} scenes predicted; the page shows the first {SCENES}")
    return page


def _capture_images(folder: Path, shape: tuple[int, int]) -> dict[str, np.ndarray]:
    """The one image per view a net reads from a capture folder, where it has them at the
    depth map's size."""
    from odmv.io.images import ImageError, find_view_image, read_image
    from odmv.rig import VIEW_NAMES

    found = {}
    for view in VIEW_NAMES:
        p = find_view_image(folder, view) if folder.is_dir() else None
        if p is None:
            continue
        try:
            img = read_image(p)
        except ImageError:
            continue
        if img.data.shape == shape:
            found[view] = img.data.astype(np.float32) / img.full_scale
    return found


def _no_truth(folder: Path) -> str:
    return (
        "no ground truth: the input is not a dataset scene"
        if folder.is_dir()
        else f"{folder}: the input is not on this machine; no input images nor ground truth"
    )
