"""The dataset contract checked: every file a manifest names, its channels, sizes and values
(:func:`validate`; ``python -m odmv.validate`` prints its report)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from odmv.io import exr
from odmv.io.images import fringe_problem, intensity_problem
from odmv.io.manifest import (
    DEPTH_CHANNEL,
    DEPTH_FILE,
    FOOTPRINT_FILE,
    FRINGE_CHANNEL,
    FRINGE_DIR,
    LIT_FILE,
    PROJ_COORD_FILE,
    SCENE_SPEC_FILE,
    Manifest,
    ManifestError,
    load_manifest,
)


@dataclass
class Report:
    problems: list[str]
    scenes: int = 0
    views: int = 0
    images: int = 0
    labelled: bool = True  # False: no scene holds ground truth (a user's rig, fringes only)

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self, root: Path) -> str:
        line = f"{root}: ok, {self.scenes} scenes, {self.views} views, {self.images} fringe images"
        if not self.labelled:
            line += "; no ground truth (fringes only: for label-free adaptation, adapt=true)"
        return line


def _holds_fringe(path: Path, m: Manifest) -> bool:
    """Whether ``path`` is a phase-shifted image whose projector lights the scene (not a
    uniform image, nor one of a view the manifest declares dark)."""
    view, _, rest = path.name.partition("_")
    return path.parent.name == FRINGE_DIR and rest[:1] == "f" and view not in m.dark_views()


def _check_image(
    path: Path,
    channels: list[str],
    shape: tuple[int, int],
    deep: bool,
    nan_depth: bool = False,
    fringe: bool = False,
) -> str | None:
    """Return a problem line, or None. ``deep`` decodes the pixels too; ``nan_depth``: the
    manifest declares NaN depth for pixels without ground truth; ``fringe``: the image must
    hold a fringe (odmv.io.images.fringe_problem)."""
    try:
        found = exr.exr_channels(path)
        missing = [c for c in channels if c not in found]
        if missing:
            return f"{path}: missing channel(s) {missing} (has {sorted(found)})"
        bad = {c: found[c] for c in channels if found[c] != shape}
        if bad:
            return f"{path}: channel shape(s) {bad} differ from the manifest's {shape}"
        if deep:
            data = exr.read_exr(path, channels)
            return _check_values(path, data, nan_depth) or (
                fringe_problem(path, data[FRINGE_CHANNEL]) if fringe else None
            )
    except exr.ExrError as e:
        return str(e)
    return None


def _check_values(path: Path, data: dict[str, np.ndarray], nan_depth: bool) -> str | None:
    name = path.name
    for c, a in data.items():
        a = a.astype(np.float32)
        if name == DEPTH_FILE and nan_depth:  # an import: its depth values as stored
            known = a[~np.isnan(a)]
            if not known.size or not np.isfinite(known).all():
                return f"{path}: depth must be finite where known (NaN marks no ground truth)"
        elif name == DEPTH_FILE and not (np.isfinite(a).all() and (a > 0).all()):
            return f"{path}: depth must be finite and positive everywhere ({np.isnan(a).sum()} NaN)"
        if name in (LIT_FILE, FOOTPRINT_FILE) and not np.isin(a, (0.0, 1.0)).all():
            return f"{path}: mask channel {c!r} has values other than 0 and 1"
        masks = (DEPTH_FILE, LIT_FILE, FOOTPRINT_FILE, PROJ_COORD_FILE)
        if name not in masks and not np.isfinite(a).all():
            return f"{path}: non-finite pixel values in channel {c!r}"
        if name not in masks:
            problem = _check_intensity(path, a)
            if problem:
                return problem
    return None


def _check_intensity(path: Path, a: np.ndarray) -> str | None:
    """Fringe images hold linear intensity (odmv.io.images.intensity_problem): a rendered or
    converted dataset's are never negative."""
    return intensity_problem(
        path,
        a,
        floor=0.0,
        negative="an import of [-1, 1] data needs python -m odmv.convert ... intensity=auto",
        bright="integer values not divided by their full scale; convert with intensity=auto",
    )


def validate(root: str | Path, deep: bool = True, scene_ids: list[str] | None = None) -> Report:
    """Check every file the manifest promises (of the scenes ``scene_ids`` only, e.g. one
    shard's). ``deep=False`` reads headers only."""
    root = Path(root)
    try:
        m: Manifest = load_manifest(root)
    except ManifestError as e:
        return Report([str(e)])
    report = Report([], scenes=len(m.scenes), views=len(m.views))
    shape = (m.height_px, m.width_px)
    views = list(m.views)
    if not m.scenes:
        report.problems.append(f"{root / 'manifest.json'}: lists no scenes")
    if m.images == "training" and m.fringe.uniform:
        report.problems.append(
            f"{root / 'manifest.json'}: fringe.uniform is true, but images=training stores no "
            "uniform images; python -m odmv.simulate with the dataset's settings rewrites it"
        )
    scenes = m.scenes if scene_ids is None else [s for s in m.scenes if s["id"] in scene_ids]
    report.scenes = len(scenes)
    # a dataset without any depth file holds fringes only; one with some lacks the others
    report.labelled = any((m.scene_dir(s["id"]) / DEPTH_FILE).exists() for s in scenes)
    for scene in scenes:
        sdir = m.scene_dir(scene["id"])
        if not sdir.is_dir():
            report.problems.append(f"{sdir}: scene folder missing")
            continue
        checks = [(p, [FRINGE_CHANNEL]) for p in m.fringe_files(scene["id"])]
        report.images += len(checks)
        if report.labelled:
            checks += [(sdir / DEPTH_FILE, [DEPTH_CHANNEL]), (sdir / LIT_FILE, views)]
            if not m.extra.get("source"):  # imported datasets have no projector coordinates
                checks.append((sdir / PROJ_COORD_FILE, views))
            if (sdir / FOOTPRINT_FILE).exists():  # optional (odmv.data.subsets)
                checks.append((sdir / FOOTPRINT_FILE, views))
        nan_depth = bool(m.extra.get("invalid_depth"))
        for path, channels in checks:
            fringe = _holds_fringe(path, m)
            problem = _check_image(path, channels, shape, deep, nan_depth, fringe)
            if problem:
                report.problems.append(problem)
        if deep and report.labelled and not any(p.startswith(str(sdir)) for p in report.problems):
            problem = _check_coords(sdir, views)
            if problem:
                report.problems.append(problem)
        spec = sdir / SCENE_SPEC_FILE
        try:
            json.loads(spec.read_text())
        except FileNotFoundError:
            report.problems.append(f"{spec}: scene spec missing")
        except (json.JSONDecodeError, UnicodeDecodeError):
            report.problems.append(f"{spec}: not valid JSON")
    return report


def _check_coords(sdir: Path, views: list[str]) -> str | None:
    """Projector coordinates must be finite exactly where the projector lights the pixel, and
    a projector lights only pixels inside its footprint."""
    lit = exr.read_exr(sdir / LIT_FILE, views)
    if (sdir / PROJ_COORD_FILE).exists():
        coord = exr.read_exr(sdir / PROJ_COORD_FILE, views)
        for v in views:
            if not np.array_equal(np.isfinite(coord[v]), lit[v] > 0.5):
                return (
                    f"{sdir / PROJ_COORD_FILE}: channel {v!r} is not finite exactly on lit pixels"
                )
    if (sdir / FOOTPRINT_FILE).exists():
        foot = exr.read_exr(sdir / FOOTPRINT_FILE, views)
        for v in views:
            if ((lit[v] > 0.5) & (foot[v] < 0.5)).any():
                return f"{sdir / FOOTPRINT_FILE}: channel {v!r} misses pixels that {v} lights"
    return None
