"""Import formats: each a reader that yields a source's samples (:class:`Sample`) and its one
entry (:class:`Importer`) in :data:`FORMATS` (``python -m odmv.convert format=NAME``; what
each reads: its reader's docstring and docs/dataset.md)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from odmv.classical.fringe import wrapped_phase
from odmv.classical.reconstruct import reconstruct_scene
from odmv.classical.sequences import PspOptions, read_stack, views_in
from odmv.io.exr import read_exr
from odmv.io.images import find_view_image, read_image
from odmv.io.manifest import DEPTH_CHANNEL
from odmv.rig import VIEW_NAMES

INTENSITIES = ("auto", "as_is")
#: Placeholder period (projector px) of imports, whose fringe period is not known.
UNKNOWN_PERIOD_PX = 30.0


class ConvertError(ValueError):
    """A one-line error naming the source file and its problem."""


class Sample(NamedTuple):
    """One source sample: its split, {view: intensity}, depth (mm, NaN: no truth), the lit
    masks where the source knows them, and its name in the source (a file, folder or index)."""

    split: str | None
    images: dict[str, np.ndarray]
    depth: np.ndarray
    source: str
    lit: dict[str, np.ndarray] | None = None


def crop16(a: np.ndarray) -> np.ndarray:
    """The central part of an image (..., H, W) whose sides are multiples of 16."""
    h, w = a.shape[-2:]
    ch, cw = h - h % 16, w - w % 16
    if min(ch, cw) == 0:
        raise ConvertError(f"images of {w}x{h} px are smaller than 16 px")
    top, left = (h - ch) // 2, (w - cw) // 2
    return a[..., top : top + ch, left : left + cw]


def intensity(a: np.ndarray, mode: str = "auto") -> tuple[np.ndarray, str]:
    """Linear intensity in [0, 1] and how it was made: integer types divided by their maximum,
    floats in [-1, 1] with negative values mapped by (x + 1) / 2, floats above 1.5 taken as
    8-bit values, other floats as they are; ``mode="as_is"``: the values as stored."""
    a = np.asarray(a)
    if mode == "as_is":
        return a.astype(np.float32), "as stored (intensity=as_is)"
    if np.issubdtype(a.dtype, np.integer):
        scale = float(np.iinfo(a.dtype).max if a.dtype != np.int32 else 65535)
        return a.astype(np.float32) / np.float32(scale), f"divided by {scale:g}"
    lo, hi = float(np.nanmin(a)), float(np.nanmax(a))
    if lo < 0 and lo >= -1.0001 and hi <= 1.0001:
        return (a.astype(np.float32) + 1) / 2, "stored in [-1, 1], mapped by (x + 1) / 2"
    if hi > 1.5:
        return a.astype(np.float32) / np.float32(255), "divided by 255 (floats above 1.5)"
    return a.astype(np.float32), "as stored (floats in [0, 1])"


def _splits(n: int) -> list[str]:
    """Contiguous train / val / test labels, 80 / 10 / 10 with at least one val and one test
    scene from three scenes on (deterministic, the source's order)."""
    n_val = n_test = max(1, round(n * 0.1)) if n >= 3 else 0
    return ["train"] * (n - n_val - n_test) + ["val"] * n_val + ["test"] * n_test


def _load_npy(path: Path) -> np.ndarray:
    if not path.is_file():
        raise ConvertError(f"{path}: no such file")
    try:
        a = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError) as e:
        raise ConvertError(f"{path}: not a readable .npy array ({e})") from None
    if a.ndim == 4 and a.shape[-1] == 1:
        a = a[..., 0]
    if a.ndim == 2:  # one sample
        a = a[None]
    if a.ndim != 3:
        raise ConvertError(f"{path}: shape {a.shape}; expected N x H x W (x 1) or H x W")
    return a


def _paired_npy(fringe: Path, depth: Path) -> tuple[np.ndarray, np.ndarray]:
    x, z = _load_npy(fringe), _load_npy(depth)
    if x.shape != z.shape:
        raise ConvertError(f"{depth}: shape {z.shape} differs from {fringe.name}'s {x.shape}")
    return x, z


def nguyen2020(src: Path, invalid_at_or_below: float = 50.0) -> Iterator[Sample]:
    """The training files give train and val (the last tenth), the test files test."""
    for part in ("train", "test"):
        x, z = _paired_npy(src / f"X_{part}_fringe.npy", src / f"Z_{part}.npy")
        n = len(x)
        labels = (
            ["train"] * (n - n // 10) + ["val"] * (n // 10) if part == "train" else ["test"] * n
        )
        for i in range(n):
            images, depth = {"right": np.asarray(x[i])}, _invalid(z[i], invalid_at_or_below)
            yield Sample(labels[i], images, depth, f"X_{part}_fringe.npy[{i}]")


def uhrnet(src: Path, invalid_at_or_below: float = -100.0) -> Iterator[Sample]:
    """The dataset's ``f1_80.npy`` / ``Z.npy``, or the sample its repository ships
    (``fringe_pattern.npy`` / ``height_map.npy``, one H x W image). Both hold height above the
    reference plane; the source's own evaluation counts Z <= -100 (the fill) as no data."""
    pairs = [("f1_80.npy", "Z.npy"), ("fringe_pattern.npy", "height_map.npy")]
    found = [(src / a, src / b) for a, b in pairs if (src / a).is_file()]
    if not found:
        raise ConvertError(f"{src}: neither f1_80.npy with Z.npy nor fringe_pattern.npy")
    x, z = _paired_npy(*found[0])
    for i, (label, xi, zi) in enumerate(zip(_splits(len(x)), x, z, strict=True)):
        images, depth = {"right": np.asarray(xi)}, _invalid(zi, invalid_at_or_below)
        yield Sample(label, images, depth, f"{found[0][0].name}[{i}]")


def fppmlbench(src: Path, invalid_at_or_below: float = 0.0) -> Iterator[Sample]:
    """PNG fringes and MAT depth maps (variable ``depth``, or the only one) of equal stems."""
    from scipy.io import loadmat

    pngs = sorted(src.rglob("*.png"))
    mats = {p.stem: p for p in src.rglob("*.mat")}
    pairs = [(p, mats[p.stem]) for p in pngs if p.stem in mats]
    if not pairs:
        raise ConvertError(f"{src}: no PNG fringe image with a MAT depth map of the same name")
    for label, (png, mat) in zip(_splits(len(pairs)), pairs, strict=True):
        try:
            data = loadmat(mat)
        except (ValueError, OSError, NotImplementedError) as e:
            raise ConvertError(f"{mat}: not a readable MAT file ({e})") from None
        keys = [k for k in data if not k.startswith("__")]
        key = "depth" if "depth" in data else (keys[0] if len(keys) == 1 else None)
        if key is None:
            raise ConvertError(f"{mat}: variables {keys}, none named 'depth'")
        image = read_image(png)
        depth = _invalid(data[key], invalid_at_or_below)
        yield Sample(label, {"right": _stored(image)}, depth, str(png.relative_to(src)))


def folder(src: Path, depth_scale: float = 1.0) -> Iterator[Sample]:
    """``src/<scene>/<view>.<ext>`` and ``depth.<exr|npy|png>``; the views are those of the
    first scene, in the rig's order."""
    scenes = sorted(d for d in src.iterdir() if d.is_dir()) if src.is_dir() else []
    if not scenes:
        raise ConvertError(f"{src}: no scene folders")
    views = [v for v in VIEW_NAMES if find_view_image(scenes[0], v)]
    if not views:
        raise ConvertError(f"{scenes[0]}: no view images ({', '.join(VIEW_NAMES)}.<ext>)")
    for label, scene in zip(_splits(len(scenes)), scenes, strict=True):
        images = {}
        for v in views:
            path = find_view_image(scene, v)
            if path is None:
                raise ConvertError(f"{scene}: no {v}.<ext> (the first scene has {views})")
            images[v] = _stored(read_image(path))
        yield Sample(label, images, _folder_depth(scene, depth_scale), scene.name)


def _scaled(image) -> np.ndarray:
    """An image file's values over its full scale (integer files); floats as stored."""
    return image.data if image.full_scale == 1 else image.data / np.float32(image.full_scale)


def _stored(image) -> np.ndarray:
    """An image file's values in their stored type (8- or 16-bit integers, floats), so that
    :func:`intensity` scales them and says how (an integer file divided by its full scale)."""
    if image.full_scale == 255:
        return image.data.astype(np.uint8)
    if image.full_scale == 65535:
        return image.data.astype(np.uint16)
    return image.data


def _folder_depth(scene: Path, depth_scale: float) -> np.ndarray:
    path = find_view_image(scene, "depth")
    if path is None:
        raise ConvertError(f"{scene}: no depth.exr, depth.npy or depth.png")
    if path.suffix.lower() == ".exr":
        channels = read_exr(path)
        depth = channels.get(DEPTH_CHANNEL, next(iter(channels.values())))
    else:
        depth = read_image(path).data  # stored units, not intensity
    return _invalid(depth.astype(np.float32) * np.float32(depth_scale), 0.0)


def _invalid(depth, at_or_below: float) -> np.ndarray:
    d = np.array(depth, dtype=np.float32)
    d[~(d > at_or_below)] = np.nan  # also NaN where the source has NaN
    return d


def sequences(src: Path, calibration=None, psp: PspOptions | None = None) -> Iterator[Sample]:
    """``src/<scene>/`` with each projector's sequences (``psp``'s names and conventions; the
    views are the calibration's projectors whose files the first scene has). Ground truth: the
    classical reconstruction with the calibration, NaN where rejected. Images: each view's full
    sequences (F, N, H, W), their steps put in the twin's order (:func:`twin_steps`). Lit:
    pixels modulated in every frequency."""
    scenes, views = sequence_scenes(src, calibration, psp)
    options, steps = psp, psp.steps
    projectors = [calibration.projectors()[v] for v in views]
    order = twin_steps(options, steps)
    for label, scene in zip(_splits(len(scenes)), scenes, strict=True):
        stack = np.stack([read_stack(scene, options, v, steps, _read_sequence) for v in views])
        h, w = stack.shape[-2:]
        depth = reconstruct_scene(stack, calibration.camera_at(w, h), projectors, options)
        lit = {}
        for v, view_stack in zip(views, stack, strict=True):
            modulation = [wrapped_phase(s, options.shift_sign)[1] for s in view_stack]
            lit[v] = np.logical_and.reduce([b >= options.min_modulation for b in modulation])
        inputs = {v: view_stack[:, order] for v, view_stack in zip(views, stack, strict=True)}
        yield Sample(label, inputs, depth.astype(np.float32), scene.name, lit)


def twin_steps(options: PspOptions, steps: int) -> list[int]:
    """For each of the twin's phase steps s (shift +2 pi s / N), the captured image whose shift
    is nearest to it: image n shifts by shift_sign 2 pi n / N + phase_origin_rad. What remains
    is one shift for all (:func:`residual_origin_rad`)."""
    origin = options.phase_origin_rad * steps / (2 * np.pi)
    return [int(np.round(options.shift_sign * (s - origin))) % steps for s in range(steps)]


def residual_origin_rad(options: PspOptions, steps: int) -> float:
    """The phase shift (rad) left on every image of the twin's order (:func:`twin_steps`):
    zero where the captured first phase is a whole number of steps."""
    origin = options.phase_origin_rad * steps / (2 * np.pi)
    return float(2 * np.pi * (origin - np.round(origin)) / steps)


def _read_sequence(scene: Path, names: list[str]) -> np.ndarray:
    """The images of ``names`` in ``scene`` (S, H, W), over their full scale."""
    images = []
    for stem in names:
        path = find_view_image(scene, stem)
        if path is None:
            raise ConvertError(f"{scene}: no image {stem}.<ext> (psp.pattern)")
        images.append(_scaled(read_image(path)))
    shapes = {im.shape for im in images}
    if len(shapes) != 1:
        raise ConvertError(f"{scene}: {names[0]}... images differ in size {sorted(shapes)}")
    return np.stack(images)


def sequence_scenes(src: Path, calibration, psp: PspOptions) -> tuple[list[Path], list[str]]:
    """The scene folders under ``src`` and the calibration's views the first one has."""
    if calibration is None:
        raise ConvertError("format=sequences: give the rig's calibration (calibration=FILE)")
    scenes = sorted(d for d in src.iterdir() if d.is_dir()) if src.is_dir() else []
    if not scenes:
        raise ConvertError(f"{src}: no scene folders")
    views = views_in(scenes[0], psp, list(calibration.projectors()))
    if not views:
        raise ConvertError(
            f"{scenes[0]}: no sequence of the calibration's projectors named like "
            f"{psp.stem(next(iter(calibration.projectors())), 0, 0, 1)} (psp.pattern)"
        )
    return scenes, views


@dataclass(frozen=True)
class Importer:
    """One import format: the reader that yields its samples and what the writer does with
    them. ``quantity``: what its depth maps hold (depth, or height above the reference plane;
    odmv.io.manifest.Manifest.quantity). ``crop``: sides cropped centrally to multiples of 16
    (not where a calibration describes the full size). ``rig``: its reader takes the rig's
    calibration and the sequences' names and conventions (``calibration``, ``psp``), and the
    dataset keeps the full sequences (``images: full``)."""

    reader: Callable[..., Iterator[Sample]]
    reads: str  # what a source holds, as the refusal of an unknown format lists it
    quantity: str = "depth"
    crop: bool = True
    rig: bool = False


#: every import format: name (``convert format=NAME``) -> its entry; a new format is a reader
#: and one entry here (docs/layout.md)
FORMATS = {
    "nguyen2020": Importer(
        nguyen2020, "X_{train,test}_fringe.npy, Z_{train,test}.npy (N x H x W x 1), depth mm"
    ),
    "uhrnet": Importer(
        uhrnet, "f1_80.npy, Z.npy (N x H x W [x 1]) or one sample's .npy, height mm", "height"
    ),
    "fppmlbench": Importer(fppmlbench, "PNG fringes and MAT depth maps of the same name"),
    "folder": Importer(folder, "SRC/<scene>/<view>.<ext> images and depth.<exr|npy|png>"),
    "sequences": Importer(
        sequences,
        "SRC/<scene>/ phase-shifting sequences, with the rig's calibration",
        crop=False,
        rig=True,
    ),  # fmt: skip
}
