"""Captures as predict reads them: a scene (a dataset's, or a folder of view images), the
scenes an ``input=`` names, camera images read as linear intensity with one line saying how they
were scaled and resized, a scene's phase-shifting sequences and its single-shot images."""

from __future__ import annotations

import glob
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from odmv.classical.reconstruct import twin_options
from odmv.classical.sequences import PspOptions, count_steps, read_stack, views_in
from odmv.data.dataset import DataError, SampleSpec, check_spec, load_scene
from odmv.io.images import IMAGE_EXTENSIONS, find_view_image, fit_to, intensity_problem, read_image
from odmv.io.manifest import MANIFEST, Manifest, load_manifest
from odmv.rig import VIEW_NAMES


@dataclass(frozen=True)
class Scene:
    """One input scene: a dataset scene (``manifest`` set) or a folder of view images."""

    folder: Path
    manifest: Manifest | None = None

    @property
    def name(self) -> str:
        return self.folder.name


def find_scenes(spec: str, names: list[str]) -> list[Scene]:
    """The scenes ``input`` names: a scene, a folder of scenes, or a glob of either; a folder
    is a scene when it has an image of one of the stems ``names``."""
    paths = (
        sorted(Path(p) for p in glob.glob(spec) if Path(p).is_dir())
        if glob.has_magic(spec)
        else [Path(spec)]
    )
    scenes = []
    for path in paths:
        scene = _as_scene(path, names)
        if scene is not None:
            scenes.append(scene)
        elif path.is_dir():
            scenes += [s for sub in sorted(path.iterdir()) if (s := _as_scene(sub, names))]
    if not scenes:
        raise DataError(
            f"input: {spec}: no scenes (a dataset scene, a folder of images such as "
            f"{names[0]}.png, or a folder of those)"
        )
    return scenes


def _as_scene(path: Path, names: list[str]) -> Scene | None:
    dataset = path.parent.parent
    if path.parent.name == "scenes" and (dataset / MANIFEST).is_file() and path.is_dir():
        return Scene(path, load_manifest(dataset))
    if path.is_dir() and any(find_view_image(path, n) for n in names):
        return Scene(path)
    return None


class ImageReader:
    """Reads a scene's view images as linear intensity at the network's size, saying once how
    it scales and resizes them (and again whenever that changes)."""

    def __init__(self, scale: float | None, fit: str):
        if scale is not None and not float(scale) > 0:
            raise DataError(f"scale: {scale}; a positive full scale (null: from the files)")
        self.scale, self.fit = scale, fit
        self._said: set[str] = set()

    def _say(self, text: str) -> None:
        if text not in self._said:
            self._said.add(text)
            print(text, flush=True)

    def read(
        self, folder: Path, stems: list[str], size: tuple[int, int] | None, fringes: bool = False
    ) -> np.ndarray:
        """The images ``stems`` of ``folder`` in full-scale units, checked (with ``fringes``:
        each must show a fringe)."""
        images = []
        for stem in stems:
            path = find_view_image(folder, stem)
            if path is None:
                raise DataError(f"{folder}: no image {stem}.<ext> ({', '.join(IMAGE_EXTENSIONS)})")
            images.append((path, read_image(path)))
        shapes = {im.data.shape for _, im in images}
        if len(shapes) != 1:
            raise DataError(f"{folder}: the view images differ in size {sorted(shapes)}")
        kinds = {(im.kind, im.full_scale) for _, im in images}
        kind, full_scale = sorted(kinds)[0]
        scale = full_scale if self.scale is None else float(self.scale)
        how = "given by scale=" if self.scale is not None else f"{kind}; override with scale="
        self._say(f"intensity: value / {scale:g} ({how})")
        stack = np.stack([im.data for _, im in images]) / np.float32(scale)
        for (path, _), image in zip(images, stack, strict=True):
            problem = intensity_problem(
                path,
                image,
                negative="a camera's intensities are not negative",
                bright=f"divided by scale={scale:g}; give the camera's full scale as scale=",
                fringe=fringes,
            )
            if problem:
                raise DataError(problem)
        if size is None:
            return stack
        stack, note = fit_to(stack, size, self.fit)
        self._say(f"size: {note}")
        return stack


@dataclass(frozen=True)
class Sequences:
    """A scene's phase-shifting sequences: (V, F, N, H, W) linear intensity, coarsest
    frequency first, the views they are of, and how to decode them."""

    stack: np.ndarray
    views: list[str]
    options: PspOptions


def read_sequences(scene: Scene, reader: ImageReader, cfg, rig) -> Sequences:
    """A dataset scene's sequences (its manifest's conventions), or a folder's named by
    ``psp.*`` (the periods from ``manifest=`` when ``psp.periods`` is not given)."""
    m = scene.manifest
    if m is not None:
        if m.images != "full":
            raise DataError(
                f"{scene.folder}: method=psp decodes each projector's full sequences, and this "
                "dataset holds the network's images only (images=training); render it with "
                "images=full"
            )
        spec = check_spec(m, m.views, [m.height_px, m.width_px], None, None, with_stacks=True)
        stack = load_scene(m, scene.name, spec)["fringe_stack"]
        h, w = stack.shape[-2:]
        coarse_first = np.argsort(m.fringe.periods_px)[::-1]
        stack = stack.reshape(len(m.views), len(coarse_first), m.fringe.steps, h, w)
        return Sequences(stack[:, coarse_first], list(m.views), twin_options(m))
    options = PspOptions.from_cfg(cfg.psp)
    if options.periods is None and cfg.manifest:
        known = twin_options(load_manifest(cfg.manifest))
        options = replace(options, periods=known.periods, steps=options.steps or known.steps)
    named = list(cfg.get("views") or [])
    if options.per_view:
        candidates = list(rig.projectors()) if rig is not None else list(VIEW_NAMES)
        views = named or views_in(scene.folder, options, candidates)
        if not views:
            raise DataError(
                f"{scene.folder}: no sequence named like {options.stem(candidates[0], 0, 0, 1)} "
                "(set psp.pattern and psp.first_index)"
            )
    elif len(named) == 1 or (not named and rig is not None and len(rig.projectors()) == 1):
        views = named or list(rig.projectors())
    else:
        raise DataError(
            f"psp.pattern {options.pattern!r} names no view: the folder holds one projector's "
            "sequences; name it with views=[NAME]"
        )
    steps = count_steps(scene.folder, options, views[0])

    def read(folder, names):
        return reader.read(folder, names, None)

    stack = np.stack([read_stack(scene.folder, options, v, steps, read) for v in views])
    return Sequences(stack, views, options)


def single_shot_images(scene: Scene, cfg, reader: ImageReader, views: list[str]):
    """The one fringe image per view that ``method=ftp`` decodes (V x H x W, linear intensity)
    and its period (projector px): a dataset scene's network image, or a folder's images of
    the fringe of ``manifest=``'s network image."""
    m = scene.manifest
    if m is None and not cfg.manifest:
        raise DataError(
            f"{scene.folder}: method=ftp needs the fringe's period and phase step: give "
            "manifest=DATASET, a dataset whose network image the captures repeat"
        )
    fringe = (m or load_manifest(cfg.manifest)).fringe
    frequency = fringe.resolve_frequency(fringe.train_frequency)
    if m is not None:
        spec = SampleSpec(tuple(views), m.height_px, m.width_px, frequency, fringe.train_step)
        images = np.array(load_scene(m, scene.name, spec)["fringes"], np.float64)
    else:
        images = reader.read(scene.folder, views, None, fringes=True).astype(np.float64)
    return images, fringe.periods_px[frequency]
