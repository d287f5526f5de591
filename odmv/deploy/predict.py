"""Depth from a user's captures, by a trained net (checkpoint or ONNX) or classically
(``method=psp``: phase shifting of full sequences; ``method=ftp``: one image per projector):
:func:`predict` writes each scene's depth.exr, preview and point cloud (what ``python -m
odmv.predict`` does; its docstring says what it reads and writes)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import matplotlib
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

from odmv.classical.fringe import period_in_camera_px
from odmv.classical.reconstruct import decode_views, fused_depth, single_shot_depth
from odmv.classical.sequences import PspOptions
from odmv.data.dataset import DataError, SampleSpec, load_scene, matching_fringe
from odmv.deploy.inference import load_predictor
from odmv.importers.captures import (
    ImageReader,
    Scene,
    find_scenes,
    read_sequences,
    single_shot_images,
)
from odmv.io.atomic import write_atomic, write_npy, write_text
from odmv.io.calibration import load_calibration
from odmv.io.exr import write_exr
from odmv.io.guard import refuse_inside
from odmv.io.images import (
    find_view_image,
    fit_to,
)
from odmv.io.manifest import (
    FRINGE_DIR,
    HEIGHT_QUANTITY,
    load_manifest,
)
from odmv.io.pointcloud import point_cloud, write_ply
from odmv.rig import VIEW_NAMES, Camera, Rig
from odmv.training.uncertainty import capture_outside, period_window_px

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

NO_RIG = "its dataset has no rig calibration (give calibration=FILE)"


def present_views(scene: Scene, predictor, named: list[str] | None) -> list[str]:
    """The predictor's views this capture has: those ``named`` (``views=``), else those with an
    image file (a dataset scene has all). A net trained with view dropout takes any non-empty
    subset; any other net needs every view it was trained on."""
    views = list(predictor.views)
    if named:
        have = [v for v in views if v in named]
        if len(have) < len(named):
            raise DataError(f"views={named}: the net knows only the views {views}")
    elif scene.manifest is None:
        have = [v for v in views if find_view_image(scene.folder, v)]
    else:
        have = views
    if have == views:
        return have
    if not predictor.input_spec.get("availability"):
        lost = [v for v in views if v not in have]
        raise DataError(
            f"{scene.folder}: no image for view(s) {', '.join(lost)}; this net needs all of "
            f"{', '.join(views)} (one trained with view_dropout takes any of them)"
        )
    if not have:
        raise DataError(f"{scene.folder}: none of the net's views {views}")
    return have


def network_images(scene: Scene, predictor, reader: ImageReader, rig: Rig, have=None):
    """S x H x W linear-intensity images of the predictor's views at its input size (a view
    not in ``have``: zeros, for the net to be told it is missing)."""
    have = list(predictor.views) if have is None else list(have)
    if scene.manifest is None and have != list(predictor.views):
        present = reader.read(scene.folder, have, predictor.size, fringes=True)
        images = np.zeros((len(predictor.views), *present.shape[1:]), np.float32)
        for k, v in enumerate(have):
            images[predictor.views.index(v)] = present[k]
        return images
    if scene.manifest is not None:
        m = scene.manifest
        frequency, step = matching_fringe(m, predictor.input_spec, predictor.views, scene.folder)
        spec = SampleSpec(tuple(predictor.views), *predictor.size, frequency, step)
        images = np.array(load_scene(m, scene.name, spec)["fringes"], np.float32)
        images[[v not in have for v in predictor.views]] = 0  # views= left them out
        return images
    return reader.read(scene.folder, predictor.views, predictor.size, fringes=True)


def expected_images(predictor) -> str:
    """What a checkpoint takes from a capture, for folders of images (nothing to check them
    against): each view's image of the fringe it was trained on."""
    spec = predictor.input_spec
    if spec.get("period_px") is None:
        return f"the checkpoint takes one image per view: {', '.join(predictor.views)}"
    return (
        f"the checkpoint takes one image per view ({', '.join(predictor.views)}) of the "
        f"{spec['period_px']:g} px fringe (period in projector px) at phase step {spec['step']} "
        f"of {spec['n_steps']}, as it was trained; other fringes give wrong depth"
    )


def lit_by_any_view(images: np.ndarray, period_camera_px: float, threshold: float) -> np.ndarray:
    """Pixels some projector lights: the brightest value within one fringe period (so a dark
    fringe of a lit surface counts as lit) above ``threshold`` (full-scale units) in a view."""
    k = period_window_px(period_camera_px)
    t = torch.from_numpy(np.ascontiguousarray(images, np.float32))[None]
    peak = torch.nn.functional.max_pool2d(t, k, stride=1, padding=k // 2)[0].numpy()
    return (peak > threshold).any(0)


def uniform_grey(scene: Scene, reader: ImageReader, views: list[str], size) -> np.ndarray | None:
    """The flat-illumination images as grey levels (uint8, the brightest view per pixel, so a
    surface any projector lights shows its albedo), or None where the scene has none."""
    if scene.manifest is not None:
        m = scene.manifest
        if not (m.fringe.uniform and m.images == "full"):
            return None
        folder, stems = m.scene_dir(scene.name) / FRINGE_DIR, [f"{v}_uniform" for v in m.views]
    else:
        folder, stems = scene.folder, [f"{v}_uniform" for v in views]
        stems = [s for s in stems if find_view_image(folder, s)]
        if not stems:
            return None
    images = reader.read(folder, stems, None)
    if size is not None:
        images, _ = fit_to(images, size, reader.fit)
    return np.round(np.clip(images.max(0), 0, 1) * 255).astype(np.uint8)


def write_preview(path: Path, depth_mm: np.ndarray) -> Path:
    """A colour-mapped PNG of the depth (near = bright), written atomically."""
    finite = depth_mm[np.isfinite(depth_mm)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    shown = np.nan_to_num(depth_mm, nan=hi)
    return write_atomic(
        path, lambda tmp: plt.imsave(tmp, shown, cmap="viridis_r", vmin=lo, vmax=hi, format="png")
    )


def predict(cfg: DictConfig) -> list[dict[str, Path]]:
    """Depth, preview and point cloud of every scene ``cfg.input`` names; returns their paths."""
    if cfg.method not in ("net", "psp", "ftp"):
        raise ValueError(f"method: {cfg.method!r} unknown; choose net, psp or ftp")
    if cfg.method == "net" and not cfg.ckpt_path:
        raise ValueError("ckpt_path: give a checkpoint or model.onnx (or method=psp)")
    predictor = load_predictor(cfg.ckpt_path) if cfg.method == "net" else None
    if cfg.get("trusted_only") and (predictor is None or predictor.error_bars is None):
        raise ValueError(
            "trusted_only: the net has no calibrated error bars (python -m odmv.study "
            "uncertainty RUN writes them beside its checkpoint)"
        )
    if predictor is not None and predictor.error_bars is not None:
        predictor.factor(float(cfg.coverage))  # refused before anything is written
    views = predictor.views if predictor else list(VIEW_NAMES)
    unknown = [v for v in cfg.get("views") or [] if v not in views]
    if unknown:  # before anything is written
        raise DataError(
            f"views={list(cfg.views)}: no view {unknown[0]!r}; "
            + (
                f"the net knows only {', '.join(views)}"
                if predictor
                else f"known views are {', '.join(views)}"
            )
        )
    if predictor is not None or cfg.method == "ftp":
        names = list(cfg.get("views") or views)
    else:
        options = PspOptions.from_cfg(cfg.psp)
        names = [options.stem(v, 0, 0, 1) for v in (cfg.get("views") or VIEW_NAMES)]
    scenes = find_scenes(str(cfg.input), names)
    default_rig = (
        load_calibration(cfg.calibration)
        if cfg.calibration
        else load_manifest(cfg.manifest).rig
        if cfg.manifest
        else None
    )
    if default_rig is None and predictor is not None and any(s.manifest is None for s in scenes):
        print(
            "rig: none given (calibration=FILE or manifest=PATH); using the paper's default rig",
            flush=True,
        )
    missing = [v for v in views if default_rig is not None and v not in default_rig.projectors()]
    if missing and predictor is not None:
        raise ValueError(f"calibration: no projector {missing[0]!r}, which the net needs")
    reader = ImageReader(cfg.scale, cfg.fit)
    if predictor is not None and any(sc.manifest is None for sc in scenes):
        print(expected_images(predictor), flush=True)
    out_root = Path(cfg.out or cfg.paths.output_dir)
    refuse_inside(
        "out",
        [out_root / s.name if len(scenes) > 1 else out_root for s in scenes],
        [s.folder for s in scenes],
        protected=[s.manifest.root for s in scenes if s.manifest is not None],
        overwrite=bool(cfg.get("overwrite")),
    )
    write_text(out_root / "predict.yaml", OmegaConf.to_yaml(cfg))  # what made these files
    results = []
    t0 = time.perf_counter()
    columns = (TextColumn("predicting"), BarColumn(), MofNCompleteColumn())
    with Progress(*columns, disable=not cfg.progress or len(scenes) < 2, transient=True) as bar:
        task = bar.add_task("scenes", total=len(scenes))
        for scene in scenes:
            out = out_root / scene.name if len(scenes) > 1 else out_root
            if predictor is not None:
                r = _by_net(scene, predictor, reader, default_rig, cfg, out)
            elif cfg.method == "ftp":
                r = _by_ftp(scene, reader, default_rig, cfg, views)
            else:
                r = _by_psp(scene, reader, default_rig, cfg, out)
            if r.depth is None:  # the phase only: depth needs the rig's calibration
                results.append({"phase": r.phases[0], "files": list(r.phases)})
                bar.advance(task)
                continue
            depth, rig, images, period, used = r.depth, r.rig, r.images, r.period, r.used
            h, w = depth.shape
            quantity = predictor.input_spec.get("quantity", "depth") if predictor else "depth"
            cam = None
            if rig is None:
                print(f"{scene.name}: no points.ply: {NO_RIG}", flush=True)
            elif quantity == "height":
                print(f"{scene.name}: no points.ply: the net predicts height, not depth")
            else:
                cam = rig.camera_at(w, h)
            keep = None
            if cfg.drop_unlit and period and cam is not None:
                proj = rig.projectors()[used[0]]
                keep = lit_by_any_view(
                    images, period_in_camera_px(period, cam, proj), cfg.unlit_threshold
                )
            grey = uniform_grey(scene, reader, used, depth.shape) if cfg.colour else None
            if r.error_bar is not None and cfg.get("trusted_only"):
                keep = r.error_bar.trusted if keep is None else keep & r.error_bar.trusted
            results.append(
                write_outputs(out, depth, cam, keep, grey, scene, cfg, quantity, r.error_bar)
            )
            bar.advance(task)
    seconds = time.perf_counter() - t0
    print(
        f"{len(scenes)} scene(s) in {seconds:.1f} s ({len(scenes) / seconds:.2f} scenes/s) "
        f"-> {out_root}",
        flush=True,
    )
    return results


class ErrorBar(NamedTuple):
    """A calibrated net's error bar at the asked coverage: each pixel's interval half width
    (mm) and whether the calibration trusts it."""

    half_width_mm: np.ndarray
    trusted: np.ndarray
    outside: str | None = None  # why the capture lies outside what it was calibrated on


class Reconstruction(NamedTuple):
    """One scene reconstructed: its depth (mm; None where only the phase could be), the rig
    it was reconstructed with, the images and fringe period (projector px) that tell lit
    pixels, the views used, and the phase files written (method=psp)."""

    depth: np.ndarray | None
    rig: Rig | None
    images: np.ndarray | None
    period: float | None
    used: list[str]
    phases: tuple[Path, ...] = ()
    error_bar: ErrorBar | None = None


def _by_net(scene: Scene, predictor, reader, default_rig, cfg, out: Path) -> Reconstruction:
    """The net's depth from the scene's images (a phase-head net's fusion weights written)."""
    rig = default_rig if scene.manifest is None else scene.manifest.rig
    rig = rig or (default_rig if scene.manifest is not None else Rig())
    have = present_views(scene, predictor, list(cfg.get("views") or []))
    if have != list(predictor.views):
        print(f"{scene.name}: views {', '.join(have)} (the others missing)", flush=True)
    images = network_images(scene, predictor, reader, rig, have)
    available = np.array([v in have for v in predictor.views], np.float32)
    x = predictor.inputs(images, rig, available)
    result = predictor.run(x, predictor.calibration(rig))
    if "weights" in result:  # head=phase: each view's share of the depth
        write_weights(out, result["weights"][0], predictor.views)
    depth = result["depth_mm"][0, 0].astype(np.float32)
    bar = None
    if "score_mm" in result:
        score = result["score_mm"][0, 0]
        trusted = score <= predictor.error_bars["trusted_score_mm"]
        outside = capture_outside(images, predictor.error_bars)
        if outside:
            print(f"{scene.name}: {outside}", flush=True)
        bar = ErrorBar(predictor.half_width_mm(score, float(cfg.coverage)), trusted, outside)
    return Reconstruction(
        depth, rig, images, predictor.input_spec.get("period_px"), predictor.views, (), bar
    )


def _by_ftp(scene: Scene, reader, default_rig, cfg, views: list[str]) -> Reconstruction:
    """Single-shot Fourier-transform profilometry of one image per projector."""
    rig = scene.manifest.rig if scene.manifest else default_rig
    used = list(cfg.get("views") or (scene.manifest.views if scene.manifest else views))
    images, period = single_shot_images(scene, cfg, reader, used)
    if rig is None:
        raise DataError(f"{scene.folder}: method=ftp: {NO_RIG}")
    m = scene.manifest or load_manifest(cfg.manifest)
    depth = single_shot_depth(images, period, m.fringe.train_step, m.fringe.steps, rig, used)
    return Reconstruction(depth.astype(np.float32), rig, images, period, used)


def _by_psp(scene: Scene, reader, default_rig, cfg, out: Path) -> Reconstruction:
    """Phase shifting of each projector's sequences: the phase written, and the fused depth
    where the rig's calibration is known."""
    rig = scene.manifest.rig if scene.manifest else default_rig
    seq = read_sequences(scene, reader, cfg, rig)
    h, w = seq.stack.shape[-2:]
    cam = rig.camera_at(w, h) if rig is not None else None
    projectors = [rig.projectors()[v] for v in seq.views] if rig is not None else None
    decoded = decode_views(seq.stack, seq.options, cam, projectors)
    phases = write_phases(out, seq.views, decoded, seq.options)
    if rig is None:
        print(
            f"{scene.name}: wrote the phase of views {', '.join(seq.views)}; depth needs the "
            "rig's calibration (calibration=FILE)",
            flush=True,
        )
        return Reconstruction(None, None, None, None, seq.views, tuple(phases))
    depth = fused_depth(decoded, cam, projectors).astype(np.float32)
    # the finest frequency's first image of each view tells lit pixels
    return Reconstruction(
        depth, rig, seq.stack[:, -1, 0], decoded[0].period, seq.views, tuple(phases)
    )


def write_phases(out: Path, views: list[str], decoded: list, options: PspOptions) -> list[Path]:
    """Per view: ``<view>_phase.exr`` and ``.npy`` (the finest frequency's unwrapped phase,
    rad, NaN where rejected; with a calibration unwrapped from the sequences the camera resolves,
    as the depth is) and ``<view>_modulation.exr`` (the fringe amplitude B of the finest
    sequence decoded, full-scale units)."""
    written = []
    out.mkdir(parents=True, exist_ok=True)
    for view, d in zip(views, decoded, strict=True):
        phase = d.phase_rad().astype(np.float32)
        what = {"unit": "rad", "odmv_quantity": "unwrapped phase of the finest frequency"}
        if options.unwrap == "spatial":
            what["odmv_quantity"] += " (spatially unwrapped: relative)"
        written.append(write_exr(out / f"{view}_phase.exr", {"Y": phase}, attributes=what))
        written.append(write_npy(out / f"{view}_phase.npy", phase))
        amplitude = {"unit": "full scale", "odmv_quantity": "fringe modulation B"}
        written.append(
            write_exr(
                out / f"{view}_modulation.exr",
                {"Y": d.modulation.astype(np.float32)},
                attributes=amplitude,
            )
        )
    return written


def write_weights(out: Path, weights: np.ndarray, views: list[str]) -> Path:
    """``weights.exr``: a phase-head net's fusion weights, one channel per view and one,
    ``regressed``, for its regressed depth (they sum to 1 at every pixel)."""
    out.mkdir(parents=True, exist_ok=True)
    channels = dict(zip([*views, "regressed"], weights.astype(np.float32), strict=True))
    return write_exr(out / "weights.exr", channels, attributes={"unit": "share of the depth"})


def write_outputs(
    out: Path,
    depth: np.ndarray,
    cam: Camera,
    keep: np.ndarray | None,
    grey: np.ndarray | None,
    scene: Scene,
    cfg,
    quantity: str = "depth",
    error_bar: ErrorBar | None = None,
) -> dict[str, Path]:
    """depth.exr (or, for a net trained on height maps, the height above the reference plane
    in it), its preview, and points.ply where a camera (``cam``) is known; with a calibrated
    net's ``error_bar``: uncertainty.exr (each pixel's interval half width, mm, at the asked
    coverage), trusted.exr (1 where the calibration trusts the pixel) and each point's
    half width in points.ply."""
    attributes = {
        "unit": "mm",
        "odmv_quantity": HEIGHT_QUANTITY
        if quantity == "height"
        else "camera-axis depth z (camera frame)",
        "odmv_method": str(cfg.method),
        "odmv_model": str(Path(cfg.ckpt_path).resolve()) if cfg.method == "net" else "psp",
        "odmv_input": str(scene.folder.resolve()),
    }
    out.mkdir(parents=True, exist_ok=True)
    written = {
        "depth": write_exr(out / "depth.exr", {"Z": depth}, attributes=attributes),
        "preview": write_preview(out / "depth.png", depth),
    }
    if error_bar is not None:
        bars = {"unit": "mm", "odmv_coverage": str(cfg.coverage)}
        bars["odmv_quantity"] = "interval half width of the depth"
        if error_bar.outside:
            bars["odmv_outside_calibration"] = error_bar.outside
        written["uncertainty"] = write_exr(
            out / "uncertainty.exr", {"Z": error_bar.half_width_mm}, attributes=bars
        )
        written["trusted"] = write_exr(
            out / "trusted.exr",
            {"Y": error_bar.trusted.astype(np.float16)},
            attributes={"odmv_quantity": "1 where the calibration trusts the depth"},
        )
    if cam is not None:
        kept = np.isfinite(depth) & (True if keep is None else keep)
        written["points"] = write_ply(
            out / "points.ply",
            point_cloud(depth, cam, keep),
            None if grey is None else grey[kept],
            None if error_bar is None else error_bar.half_width_mm[kept],
        )
    return written
