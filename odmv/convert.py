"""Import FPP datasets into the odmv dataset contract:
``python -m odmv.convert format=NAME src=PATH out=PATH``.

Formats (docs/dataset.md, "Importing datasets" and "A dataset from your own rig"):

- ``nguyen2020``: ``X_{train,test}_fringe.npy`` and ``Z_{train,test}.npy`` (N x H x W x 1), depth
  in mm, Z <= 50 invalid (Nguyen et al., Sensors 2020).
- ``uhrnet``: ``f1_80.npy`` and ``Z.npy`` (N x H x W [x 1]), or one sample as
  ``fringe_pattern.npy`` and ``height_map.npy`` (H x W): height above the reference plane in
  mm, Z <= -100 invalid.
- ``fppmlbench``: PNG fringe images and MAT depth maps of the same name (two folders under
  ``src``), depth <= 0 invalid.
- ``folder``: ``src/<scene>/<view>.<ext>`` images (odmv.io.images) and ``depth.<exr|npy|png>``
  per scene, depth <= 0 or NaN invalid (``depth_scale`` mm per stored unit).
- ``sequences``: ``src/<scene>/`` holds each projector's phase-shifting sequences (named by
  ``psp.*``, odmv.classical.sequences); with ``calibration=`` the ground truth is their classical
  reconstruction (NaN where rejected) and the input one image of the finest frequency.

Invalid pixels become NaN depth (the manifest declares ``invalid_depth``), and the lit and
footprint masks are the valid pixels (for sequences: the modulated ones). Sizes that are not
multiples of 16 are cropped centrally to the largest multiple of 16 (sequences keep their
size, which their calibration describes). Intensities become linear in [0, 1] (``intensity``:
``auto`` says what it did; ``as_is`` keeps them). The manifest records the source and what is
not known: no rig calibration (``rig: null``, ``rig_known: false``; the reference-phase input
and point clouds are refused) and no fringe period (``periods_px`` is a placeholder). Depth is
normalized with the dataset's own range over its valid pixels (``depth_range_mm``). The output
appears only when complete.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path
from typing import NamedTuple

import numpy as np
from omegaconf import DictConfig

from odmv.classical.fringe import wrapped_phase
from odmv.classical.row import reconstruct_scene
from odmv.classical.sequences import PspOptions, count_steps, read_stack, views_in
from odmv.cli import app, run_app
from odmv.io.calibration import load_calibration
from odmv.io.exr import read_exr, write_exr
from odmv.io.guard import refuse_inside
from odmv.io.images import find_view_image, read_image
from odmv.io.manifest import (
    DEPTH_CHANNEL,
    DEPTH_FILE,
    FOOTPRINT_FILE,
    FRINGE_CHANNEL,
    FRINGE_DIR,
    HEIGHT_QUANTITY,
    LIT_FILE,
    SCENE_SPEC_FILE,
    FringeSpec,
    Manifest,
    fringe_name,
)
from odmv.rig import VIEW_NAMES

FORMATS = ("nguyen2020", "uhrnet", "fppmlbench", "folder", "sequences")
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
    classical reconstruction with the calibration, NaN where rejected. Input: the finest
    frequency's image at the twin's phase step ``train_step`` (0), i.e. the capture's image
    whose shift is nearest to it. Lit: pixels modulated in every frequency."""
    scenes, views = _sequence_scenes(src, calibration, psp)
    options, steps = psp, psp.steps
    projectors = [calibration.projectors()[v] for v in views]
    origin_steps = options.phase_origin_rad * steps / (2 * np.pi)
    first = int(np.round(options.shift_sign * -origin_steps)) % steps  # its shift nearest 0
    for label, scene in zip(_splits(len(scenes)), scenes, strict=True):
        stack = np.stack([read_stack(scene, options, v, steps, _read_sequence) for v in views])
        h, w = stack.shape[-2:]
        depth = reconstruct_scene(stack, calibration.camera_at(w, h), projectors, options)
        lit = {}
        for v, view_stack in zip(views, stack, strict=True):
            modulation = [wrapped_phase(s, options.shift_sign)[1] for s in view_stack]
            lit[v] = np.logical_and.reduce([b >= options.min_modulation for b in modulation])
        inputs = {v: view_stack[-1, first] for v, view_stack in zip(views, stack, strict=True)}
        yield Sample(label, inputs, depth.astype(np.float32), scene.name, lit)


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


def _sequence_scenes(src: Path, calibration, psp: PspOptions) -> tuple[list[Path], list[str]]:
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


READERS = {
    "nguyen2020": nguyen2020,
    "uhrnet": uhrnet,
    "fppmlbench": fppmlbench,
    "folder": folder,
    "sequences": sequences,
}
#: What each format's depth maps hold (odmv.io.manifest.Manifest.quantity).
QUANTITY = {"uhrnet": "height"}


def convert(
    fmt: str,
    src: str | Path,
    out: str | Path,
    intensity: str = "auto",
    calibration: str | Path | None = None,
    psp: PspOptions | None = None,
    **options,
) -> Manifest:
    """Write the dataset at ``out`` (which must not exist) from ``src`` in format ``fmt``;
    ``calibration`` and ``psp`` are the sequences format's."""
    if fmt not in READERS:
        raise ConvertError(f"format: {fmt!r} unknown; choose {', '.join(FORMATS)}")
    if intensity not in INTENSITIES:
        raise ConvertError(f"intensity: {intensity!r} unknown; choose {', '.join(INTENSITIES)}")
    src, out = Path(src), Path(out)
    if not src.exists():
        raise ConvertError(f"{src}: no such file or folder")
    refuse_inside("out", [out], [src])
    if out.exists() and any(out.iterdir()):
        raise ConvertError(f"{out}: exists and is not empty; choose another out=")
    rig = load_calibration(calibration) if calibration else None
    if fmt == "sequences":
        psp = psp or PspOptions()
        scenes, views = _sequence_scenes(src, rig, psp)
        psp = replace(psp, steps=count_steps(scenes[0], psp, views[0]))
        options |= {"calibration": rig, "psp": psp}
    elif rig is not None:
        raise ConvertError(f"calibration: format={fmt} takes none (only format=sequences)")
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        samples = READERS[fmt](src, **options)
        manifest = _write(samples, tmp, fmt, src, options, intensity, calibration)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    manifest.root = out
    return manifest


def _write(
    samples: Iterator[Sample],
    root: Path,
    fmt: str,
    src: Path,
    options: dict,
    mode: str,
    calibration_file=None,
) -> Manifest:
    rig, psp = options.pop("calibration", None), options.pop("psp", None)
    source = {"format": fmt, "path": str(src.resolve()), "options": dict(options)}
    if calibration_file:
        source["calibration"] = str(Path(calibration_file).resolve())
    extra = {"source": source, "rig_known": rig is not None}
    if psp is None:
        fringe = FringeSpec((UNKNOWN_PERIOD_PX,), 1, False, 0, 0)
        extra["fringe_period_known"] = False  # fringe.periods_px is a placeholder
    else:
        proj = next(iter(rig.projectors().values()))
        axis_px = proj.width_px if proj.phase_axis == "u" else proj.height_px
        periods_px = tuple(axis_px / p for p in psp.frequencies)
        fringe = FringeSpec(periods_px, psp.steps, False, len(periods_px) - 1, 0)
        source["decoder"] = asdict(psp) | {"method": "odmv.classical.row.reconstruct_scene"}
    input_name = partial(fringe_name, frequency=len(fringe.periods_px) - 1, step=0)
    scenes, shape, views, hows = [], None, None, set()
    lo, hi = np.inf, -np.inf
    crop = crop16 if fmt != "sequences" else np.asarray  # a calibration describes the full size
    for index, (label, images, depth, source_name, lit) in enumerate(samples):
        sid = f"{index:06d}"
        depth = crop(depth)
        if shape is None:
            shape, views = depth.shape, list(images)
        if depth.shape != shape or list(images) != views:
            raise ConvertError(f"{src}: sample {index} differs in size or views from the first")
        finite = depth[np.isfinite(depth)]
        if finite.size:
            lo, hi = min(lo, float(finite.min())), max(hi, float(finite.max()))
        d = root / "scenes" / sid
        for v, image in images.items():
            image, how = intensity(crop(np.asarray(image)), mode)
            bad = int((~np.isfinite(image)).sum())
            if bad:
                raise ConvertError(
                    f"{src}: sample {index} ({label or 'no split'}), view {v}: {bad} fringe "
                    "pixel(s) are not finite (NaN or infinite); only depth may be NaN (no truth)"
                )
            if how not in hows:
                hows.add(how)
                print(f"intensity: {src}: {how}", flush=True)
            write_exr(d / FRINGE_DIR / input_name(v), {FRINGE_CHANNEL: image})
        valid = np.isfinite(depth)
        masks = lit if lit else dict.fromkeys(views, valid)
        masks = {v: crop(masks[v]).astype(np.float16) for v in views}
        write_exr(d / DEPTH_FILE, {DEPTH_CHANNEL: depth})
        write_exr(d / LIT_FILE, masks)
        write_exr(d / FOOTPRINT_FILE, masks)
        spec = {"id": sid, "source_index": index, "source_name": source_name}
        (d / SCENE_SPEC_FILE).write_text(json.dumps(spec) + "\n")
        scenes.append({"id": sid, "split": label})
    if not scenes or not np.isfinite(lo):
        raise ConvertError(f"{src}: no samples with valid depth")
    source["intensity"] = sorted(hows)
    if QUANTITY.get(fmt) == "height":
        extra["quantity"] = HEIGHT_QUANTITY
    extra |= {"invalid_depth": "nan", "depth_range_mm": [lo, hi]}
    manifest = Manifest(
        root=root,
        height_px=int(shape[0]),
        width_px=int(shape[1]),
        views=tuple(views),
        fringe=fringe,
        rig=rig,
        images="training",
        scenes=scenes,
        extra=extra,
    )
    manifest.write()
    return manifest


@app("convert")
def main(cfg: DictConfig) -> None:
    options = {k: v for k, v in (cfg.options or {}).items()}

    def run():
        psp = PspOptions.from_cfg(cfg.psp) if cfg.format == "sequences" else None
        return convert(cfg.format, cfg.src, cfg.out, cfg.intensity, cfg.calibration, psp, **options)

    m = run_app(run)
    counts = {s: sum(x["split"] == s for x in m.scenes) for s in ("train", "val", "test")}
    print(
        f"{m.root}: {len(m.scenes)} scenes ({counts['train']} train, {counts['val']} val, "
        f"{counts['test']} test), {m.width_px}x{m.height_px} px, views {', '.join(m.views)}; "
        f"check it with python -m odmv.validate {m.root}"
    )


if __name__ == "__main__":
    main()
