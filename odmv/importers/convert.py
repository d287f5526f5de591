"""A source converted into the odmv dataset contract: :func:`convert`, what ``python -m
odmv.convert`` runs (the formats: odmv.importers.formats).

Invalid pixels become NaN depth (the manifest declares ``invalid_depth``), and the lit and
footprint masks are the valid pixels (for sequences: the modulated ones). Sizes that are not
multiples of 16 are cropped centrally to the largest multiple of 16 (formats read with a
calibration keep their size, which it describes). Intensities become linear in [0, 1]
(``intensity``: ``auto`` says what it did; ``as_is`` keeps them). The manifest records the
source and what is not known: no rig calibration (``rig: null``, ``rig_known: false``; the
reference-phase input and point clouds are refused) and no fringe period (``periods_px`` is a
placeholder). Depth is normalized with the dataset's own range over its valid pixels
(``depth_range_mm``). The output appears only when complete.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterator
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path

import numpy as np

from odmv.classical.sequences import PspOptions, count_steps
from odmv.importers.formats import (
    FORMATS,
    INTENSITIES,
    UNKNOWN_PERIOD_PX,
    ConvertError,
    Sample,
    crop16,
    intensity,
    residual_origin_rad,
    sequence_scenes,
)
from odmv.io.calibration import load_calibration
from odmv.io.exr import write_exr
from odmv.io.guard import refuse_inside
from odmv.io.manifest import (
    DEPTH_CHANNEL,
    DEPTH_FILE,
    FOOTPRINT_FILE,
    FRINGE_CHANNEL,
    FRINGE_DIR,
    HEIGHT_QUANTITY,
    LIT_FILE,
    MANIFEST,
    SCENE_SPEC_FILE,
    FringeSpec,
    Manifest,
    fringe_name,
    load_manifest,
)


def convert(
    fmt: str,
    src: str | Path,
    out: str | Path,
    intensity: str = "auto",
    calibration: str | Path | None = None,
    psp: PspOptions | None = None,
    manifest: str | Path | None = None,
    **options,
) -> Manifest:
    """Write the dataset at ``out`` (which must not exist) from ``src`` in format ``fmt``;
    ``calibration`` (a file) or ``manifest`` (a dataset whose rig it is), and ``psp``, are the
    sequences format's."""
    if fmt not in FORMATS:
        known = "; ".join(f"{k} ({e.reads})" for k, e in FORMATS.items())
        raise ConvertError(f"format: {fmt!r} unknown; choose one of {known}")
    entry = FORMATS[fmt]
    if intensity not in INTENSITIES:
        raise ConvertError(f"intensity: {intensity!r} unknown; choose {', '.join(INTENSITIES)}")
    src, out = Path(src), Path(out)
    if not src.exists():
        raise ConvertError(f"{src}: no such file or folder")
    refuse_inside("out", [out], [src])
    if out.exists() and any(out.iterdir()):
        raise ConvertError(f"{out}: exists and is not empty; choose another out=")
    if calibration and manifest:
        raise ConvertError("calibration, manifest: give one rig, not both")
    rig = load_calibration(calibration) if calibration else None
    if manifest:
        rig = load_manifest(manifest).rig
        if rig is None:
            raise ConvertError(f"manifest: {manifest} has no rig calibration")
        calibration = Path(manifest) / MANIFEST
    if entry.rig:
        psp = psp or PspOptions()
        scenes, views = sequence_scenes(src, rig, psp)
        psp = replace(psp, steps=count_steps(scenes[0], psp, views[0]))
        options |= {"calibration": rig, "psp": psp}
    elif rig is not None:
        raise ConvertError(
            f"{'manifest' if manifest else 'calibration'}: format={fmt} takes none (only "
            f"format={', '.join(k for k, e in FORMATS.items() if e.rig)})"
        )
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        samples = entry.reader(src, **options)
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
        source["decoder"] = asdict(psp) | {"method": "odmv.classical.reconstruct.reconstruct_scene"}
        # the sequences as stored: the twin's step order, one shift left on all, and how the
        # classical target decodes them (odmv.classical.reconstruct.twin_options)
        extra["sequences"] = {
            "phase_origin_rad": residual_origin_rad(psp, psp.steps),
            "unwrap": psp.unwrap,
            "min_modulation": psp.min_modulation,
        }
    input_name = partial(fringe_name, frequency=len(fringe.periods_px) - 1, step=0)
    scenes, shape, views, hows = [], None, None, set()
    lo, hi = np.inf, -np.inf
    crop = crop16 if FORMATS[fmt].crop else np.asarray
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
        for v, stored in images.items():
            stored = np.asarray(stored)
            if stored.ndim == 2:  # the network's image alone
                named = {input_name(v): stored}
            else:  # full sequences (F, N, H, W)
                named = {
                    fringe_name(v, f, n): stored[f, n]
                    for f in range(stored.shape[0])
                    for n in range(stored.shape[1])
                }
            for name, raw in named.items():
                image, how = intensity(crop(raw), mode)
                bad = int((~np.isfinite(image)).sum())
                if bad:
                    raise ConvertError(
                        f"{src}: sample {index} ({label or 'no split'}), view {v}: {bad} fringe "
                        "pixel(s) are not finite (NaN or infinite); only depth may be NaN (no "
                        "truth)"
                    )
                if how not in hows:
                    hows.add(how)
                    print(f"intensity: {src}: {how}", flush=True)
                write_exr(d / FRINGE_DIR / name, {FRINGE_CHANNEL: image})
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
    if FORMATS[fmt].quantity == "height":
        extra["quantity"] = HEIGHT_QUANTITY
    extra |= {"invalid_depth": "nan", "depth_range_mm": [lo, hi]}
    manifest = Manifest(
        root=root,
        height_px=int(shape[0]),
        width_px=int(shape[1]),
        views=tuple(views),
        fringe=fringe,
        rig=rig,
        images="training" if psp is None else "full",
        scenes=scenes,
        extra=extra,
    )
    manifest.write()
    return manifest
