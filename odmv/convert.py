"""Import public single-shot FPP datasets into the odmv dataset contract:
``python -m odmv.convert format=NAME src=PATH out=PATH``.

Formats (docs/dataset.md, "Importing datasets"):

- ``nguyen2020``: ``X_{train,test}_fringe.npy`` and ``Z_{train,test}.npy`` (N x H x W x 1), depth
  in mm, Z <= 50 invalid (Nguyen et al., Sensors 2020).
- ``uhrnet``: ``f1_80.npy`` and ``Z.npy`` (N x H x W [x 1]), Z <= -100 invalid.
- ``fppmlbench``: PNG fringe images and MAT depth maps of the same name (two folders under
  ``src``), depth <= 0 invalid.
- ``folder``: ``src/<scene>/<view>.<ext>`` images (odmv.io.images) and ``depth.<exr|npy|png>``
  per scene, depth <= 0 or NaN invalid (``depth_scale`` mm per stored unit).

Invalid pixels become NaN depth (the manifest declares ``invalid_depth``), and the lit and
footprint masks are the valid pixels. Sizes that are not multiples of 16 are cropped centrally
to the largest multiple of 16. The manifest records the source and what is not known: no rig
calibration (the rig entry is a placeholder, ``rig_known: false``; the reference-phase input
is refused) and no fringe period (``periods_px`` is a placeholder). Depth is normalized with the
dataset's own range (``depth_range_mm``). The output appears only when complete.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from odmv.cli import run_app
from odmv.config import CONF_DIR
from odmv.io.exr import read_exr, write_exr
from odmv.io.images import find_view_image, read_image
from odmv.io.manifest import (
    DEPTH_CHANNEL,
    DEPTH_FILE,
    FOOTPRINT_FILE,
    FRINGE_CHANNEL,
    FRINGE_DIR,
    LIT_FILE,
    SCENE_SPEC_FILE,
    FringeSpec,
    Manifest,
    fringe_name,
)
from odmv.rig import VIEW_NAMES, Rig

FORMATS = ("nguyen2020", "uhrnet", "fppmlbench", "folder")
#: Placeholder period (projector px) of imports, whose fringe period is not known.
UNKNOWN_PERIOD_PX = 30.0


class ConvertError(ValueError):
    """A one-line error naming the source file and its problem."""


Sample = tuple[str, dict[str, np.ndarray], np.ndarray]  # split, {view: intensity}, depth (mm)


def crop16(a: np.ndarray) -> np.ndarray:
    """The central part of an image (..., H, W) whose sides are multiples of 16."""
    h, w = a.shape[-2:]
    ch, cw = h - h % 16, w - w % 16
    if min(ch, cw) == 0:
        raise ConvertError(f"images of {w}x{h} px are smaller than 16 px")
    top, left = (h - ch) // 2, (w - cw) // 2
    return a[..., top : top + ch, left : left + cw]


def intensity(a: np.ndarray) -> tuple[np.ndarray, float]:
    """Linear intensity in [0, 1] and the full-scale value it was divided by: integer types by
    their maximum, floats above 1.5 taken as 8-bit values, other floats as they are."""
    if np.issubdtype(a.dtype, np.integer):
        scale = float(np.iinfo(a.dtype).max if a.dtype != np.int32 else 65535)
    else:
        scale = 255.0 if float(np.nanmax(a)) > 1.5 else 1.0
    return (a.astype(np.float32) / np.float32(scale)), scale


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
    if a.ndim != 3:
        raise ConvertError(f"{path}: shape {a.shape}; expected N x H x W (x 1)")
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
            yield labels[i], {"right": np.asarray(x[i])}, _invalid(z[i], invalid_at_or_below)


def uhrnet(src: Path, invalid_at_or_below: float = -100.0) -> Iterator[Sample]:
    x, z = _paired_npy(src / "f1_80.npy", src / "Z.npy")
    for label, xi, zi in zip(_splits(len(x)), x, z, strict=True):
        yield label, {"right": np.asarray(xi)}, _invalid(zi, invalid_at_or_below)


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
        yield (
            label,
            {"right": image.data / image.full_scale},
            _invalid(data[key], invalid_at_or_below),
        )


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
            im = read_image(path)
            images[v] = im.data / im.full_scale
        yield label, images, _folder_depth(scene, depth_scale)


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


READERS = {"nguyen2020": nguyen2020, "uhrnet": uhrnet, "fppmlbench": fppmlbench, "folder": folder}


def convert(fmt: str, src: str | Path, out: str | Path, **options) -> Manifest:
    """Write the dataset at ``out`` (which must not exist) from ``src`` in format ``fmt``."""
    if fmt not in READERS:
        raise ConvertError(f"format: {fmt!r} unknown; choose {', '.join(FORMATS)}")
    src, out = Path(src), Path(out)
    if not src.exists():
        raise ConvertError(f"{src}: no such file or folder")
    if out.exists() and any(out.iterdir()):
        raise ConvertError(f"{out}: exists and is not empty; choose another out=")
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        manifest = _write(READERS[fmt](src, **options), tmp, fmt, src, options)
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    manifest.root = out
    return manifest


def _write(samples: Iterator[Sample], root: Path, fmt: str, src: Path, options: dict) -> Manifest:
    scenes, shape, views, scales = [], None, None, set()
    lo, hi = np.inf, -np.inf
    for index, (label, images, depth) in enumerate(samples):
        sid = f"{index:06d}"
        depth = crop16(depth)
        if shape is None:
            shape, views = depth.shape, list(images)
        if depth.shape != shape or list(images) != views:
            raise ConvertError(f"{src}: sample {index} differs in size or views from the first")
        finite = depth[np.isfinite(depth)]
        if finite.size:
            lo, hi = min(lo, float(finite.min())), max(hi, float(finite.max()))
        d = root / "scenes" / sid
        for v, image in images.items():
            image = crop16(np.asarray(image))
            if image.dtype != np.float32 or image.max(initial=0) > 1.5:
                image, scale = intensity(image)
                scales.add(scale)
            write_exr(
                d / FRINGE_DIR / fringe_name(v, 0, 0), {FRINGE_CHANNEL: image.astype(np.float32)}
            )
        valid = np.isfinite(depth).astype(np.float16)
        write_exr(d / DEPTH_FILE, {DEPTH_CHANNEL: depth})
        write_exr(d / LIT_FILE, dict.fromkeys(views, valid))
        write_exr(d / FOOTPRINT_FILE, dict.fromkeys(views, valid))
        (d / SCENE_SPEC_FILE).write_text(json.dumps({"id": sid, "source_index": index}) + "\n")
        scenes.append({"id": sid, "split": label})
    if not scenes or not np.isfinite(lo):
        raise ConvertError(f"{src}: no samples with valid depth")
    manifest = Manifest(
        root=root,
        height_px=int(shape[0]),
        width_px=int(shape[1]),
        views=tuple(views),
        fringe=FringeSpec((UNKNOWN_PERIOD_PX,), 1, False, 0, 0),
        rig=Rig(),
        images="training",
        scenes=scenes,
        extra={
            "source": {
                "format": fmt,
                "path": str(src.resolve()),
                "options": options,
                "intensity_scale": sorted(scales) or "as stored",
            },
            "rig_known": False,  # the rig entry is a placeholder: no calibration came with it
            "fringe_period_known": False,  # fringe.periods_px is a placeholder
            "invalid_depth": "nan",
            "depth_range_mm": [lo, hi],
        },
    )
    manifest.write()
    return manifest


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="convert")
def main(cfg: DictConfig) -> None:
    options = {k: v for k, v in (cfg.options or {}).items()}
    m = run_app(lambda: convert(cfg.format, cfg.src, cfg.out, **options))
    counts = {s: sum(x["split"] == s for x in m.scenes) for s in ("train", "val", "test")}
    print(
        f"{m.root}: {len(m.scenes)} scenes ({counts['train']} train, {counts['val']} val, "
        f"{counts['test']} test), {m.width_px}x{m.height_px} px, views {', '.join(m.views)}; "
        f"check it with python -m odmv.validate {m.root}"
    )


if __name__ == "__main__":
    main()
