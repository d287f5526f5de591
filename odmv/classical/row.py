"""The classical reference as a model row: phase shifting on every projector, triangulation,
fusion over the projectors that lit each pixel (odmv.classical.fringe), scored like a network.

``classical_row(root, out_dir)`` reads the full sequences of the test scenes, writes the same
files a trained run's test writes (``metrics.json``, ``test_scenes.csv``,
``test_predictions.npz``; NaN where nothing is reconstructed) and returns the metrics. Errors are
over the reconstructed pixels of each subset; ``coverage`` is the share of the subset's valid
pixels that is reconstructed.

A :class:`Capture` makes the row see fewer images per projector, down to the one image a
network sees (single-shot Fourier-transform profilometry): what learning adds is measured
against what the classical method does with the same images (:data:`CAPTURES`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from odmv.classical.fringe import (
    anchor_to_plane,
    decode_phase,
    demodulate,
    fuse_views,
    period_in_camera_px,
    triangulate_depth,
    unwrap_spatial,
    view_deviations_mm,
    wrapped_phase,
)
from odmv.classical.geometry import triangulation_maps
from odmv.classical.sequences import PspOptions
from odmv.data.dataset import DataError, check_spec, load_scene, load_stack, split_scenes
from odmv.data.subsets import MASKS
from odmv.io.atomic import write_json
from odmv.io.manifest import Manifest, load_manifest
from odmv.io.runfolder import METRICS, portable_record
from odmv.training.metrics import SUBSETS, DepthErrors, per_image_subset_errors, subset_suffix
from odmv.training.module import subset_masks, write_test_outputs
from odmv.training.provenance import provenance

#: Settings of the classical pipeline (documented in docs/reproduce.md).
MIN_PERIOD_CAMERA_PX = 3.0  # finer sequences alias in the camera and are left out
MIN_MODULATION = 0.02  # fringe amplitude B in full-scale units (noise std is about 0.003)
TOLERANCE_MM = 0.1  # views further than this from the per-pixel median do not count
EDGE_MM = 0.3  # mixed-pixel rejection against the 3 x 3 median


def twin_options(m) -> PspOptions:
    """The decoding options of a dataset's sequences: the twin's conventions, with what a
    converted capture's manifest says of its own (``sequences``: the first phase left after
    its steps were put in the twin's order, its unwrapping and rejection level)."""
    proj = next(iter(m.rig.projectors().values()))
    axis_px = proj.width_px if proj.phase_axis == "u" else proj.height_px
    periods = tuple(axis_px / p for p in sorted(m.fringe.periods_px, reverse=True))
    own = m.extra.get("sequences") or {}
    return PspOptions(
        periods=periods,
        steps=m.fringe.steps,
        phase_origin_rad=own.get("phase_origin_rad", 0.0),
        min_modulation=own.get("min_modulation", MIN_MODULATION),
        unwrap=own.get("unwrap", "temporal"),
    )


@dataclass(frozen=True)
class DecodedView:
    """One projector's sequences decoded: the coordinate ``u`` along its phase axis, the period
    of its finest frequency in the same unit (whether decoded or left out as aliased), the
    modulation B of the finest sequence decoded (full-scale units) and the pixels kept."""

    u: np.ndarray
    period: float
    modulation: np.ndarray
    ok: np.ndarray

    def phase_rad(self) -> np.ndarray:
        """The unwrapped phase of the finest frequency (rad), NaN where rejected."""
        return np.where(self.ok, 2 * np.pi * self.u / self.period, np.nan)


def decode_views(stack: np.ndarray, options: PspOptions, camera=None, projectors=None):
    """Full sequences (V, F, N, H, W; frequencies in the order of ``options.frequencies``) ->
    one :class:`DecodedView` per view. With the rig (``camera`` and a list of ``projectors``):
    ``u`` in projector px, from the sequences whose period the camera resolves (finer ones
    alias); without: in projector widths, from every sequence."""
    decoded = []
    for i, view_stack in enumerate(stack):
        if projectors is None:
            periods = [1 / f for f in options.frequencies]
            used = list(range(len(periods)))
        else:
            periods, used = _resolved(camera, projectors[i], options)
        u, modulation, ok, _ = decode_phase(
            view_stack[used],
            [periods[k] for k in used],
            options.min_modulation,
            **options.conventions(),
        )
        decoded.append(DecodedView(u, min(periods), modulation, ok))
    return decoded


def _resolved(camera, proj, options: PspOptions) -> tuple[list[float], list[int]]:
    """The periods of ``options``' frequencies in projector px and the indices of those the
    camera resolves; refused when that leaves out the coarsest (nothing to unwrap from)."""
    axis_px = proj.width_px if proj.phase_axis == "u" else proj.height_px
    periods_px = [axis_px / p for p in options.frequencies]
    used = [
        i
        for i, p in enumerate(periods_px)
        if period_in_camera_px(p, camera, proj) >= MIN_PERIOD_CAMERA_PX
    ]
    if not used or max(periods_px[i] for i in used) < max(periods_px):
        raise DataError(
            f"classical: the camera does not resolve the coarsest fringes "
            f"(periods {list(options.frequencies)} across the projector)"
        )
    return periods_px, used


def view_depths(decoded: list[DecodedView], camera, projectors) -> np.ndarray:
    """Views decoded with the rig (:func:`decode_views`) -> each one's triangulated depth
    (V, H, W; mm, NaN where rejected)."""
    depths = []
    for view, proj in zip(decoded, projectors, strict=True):
        depth = triangulate_depth(view.u, camera, proj)
        depths.append(np.where(view.ok & np.isfinite(depth), depth, np.nan))
    return np.stack(depths)


def fused_depth(decoded: list[DecodedView], camera, projectors) -> np.ndarray:
    """Views decoded with the rig (:func:`decode_views`) -> depth (mm, NaN where rejected):
    each view triangulated, then fused over the views that agree."""
    return _fused(decoded, view_depths(decoded, camera, projectors))


def _fused(decoded: list[DecodedView], depths: np.ndarray) -> np.ndarray:
    """The views' triangulated ``depths`` (:func:`view_depths`) fused over those that agree."""
    modulations = np.stack([view.modulation for view in decoded])
    return fuse_views(depths, modulations, TOLERANCE_MM, EDGE_MM)


def reconstruct_scene(stack: np.ndarray, camera, projectors, options: PspOptions) -> np.ndarray:
    """Full sequences (V, F, N, H, W; frequencies in the order of ``options.frequencies``) of
    the projectors ``projectors`` (a list) -> depth (mm, NaN where rejected), using the
    sequences whose period the camera resolves."""
    return fused_depth(decode_views(stack, options, camera, projectors), camera, projectors)


def classical_depths(
    m: Manifest, ids: list[str], size: tuple[int, int]
) -> tuple[dict, dict[str, float]]:
    """Each scene of ``ids`` of the dataset of manifest ``m`` (with its full sequences)
    reconstructed classically from its images resized to ``size`` (H, W) -> {scene id: depth
    (mm, H x W, NaN where nothing is reconstructed)}, and each projector's mean deviation (mm)
    from the views' per-pixel median over those scenes (:func:`view_deviations_mm`; by view,
    those that share pixels with another): a calibration that describes the rig leaves them
    near zero whatever the optics, a projector moved since calibrating shifts its own. Reads
    no labels: a user's captures will do."""
    if m.images != "full":
        raise DataError(
            f"{m.root}: the classical reconstruction needs the full phase-shifting sequences "
            f"(images=full), not images={m.images}"
        )
    h, w = size
    cam = m.rig.camera_at(w, h)
    projectors = [m.rig.projectors()[v] for v in m.views]
    n_f, n_s = len(m.fringe.periods_px), m.fringe.steps
    coarse_first = np.argsort(m.fringe.periods_px)[::-1]
    options = twin_options(m)
    depths, sums, counts = {}, np.zeros(len(m.views)), np.zeros(len(m.views))
    for sid in ids:
        stack = load_stack(m, sid, m.views, h, w).reshape(len(m.views), n_f, n_s, h, w)
        decoded = decode_views(stack[:, coarse_first], options, cam, projectors)
        per_view = view_depths(decoded, cam, projectors)
        depths[sid] = _fused(decoded, per_view)
        s, c = view_deviations_mm(per_view)
        sums, counts = sums + s, counts + c
    offsets = {v: float(s / c) for v, s, c in zip(m.views, sums, counts, strict=True) if c}
    return depths, offsets


@dataclass(frozen=True)
class Capture:
    """The images a classical row decodes per projector: ``steps`` phase-shifted images (a
    divisor of the dataset's steps, evenly spaced from the network's step) of the network's
    fringe, and with ``frequencies`` 2 as many of the one-period fringe too. One frequency is
    unwrapped spatially and its fringe order anchored to the reference plane
    (:func:`odmv.classical.fringe.anchor_to_plane`); one step of it is single-shot Fourier-transform
    profilometry (:func:`odmv.classical.fringe.demodulate`) of exactly the image a network sees."""

    steps: int
    frequencies: int = 1
    tolerance_mm: float = TOLERANCE_MM  # fusion: views further from the median do not count
    edge_mm: float = EDGE_MM  # fusion: mixed-pixel rejection against the 3 x 3 median

    @property
    def images(self) -> int:
        return self.steps * self.frequencies

    @property
    def label(self) -> str:
        if self.images == 1:
            return "Fourier transform, 1 image"
        fringes = "the network's fringe" if self.frequencies == 1 else "2 frequencies"
        return f"{self.steps}-step, {fringes}, {self.images} images"

    @property
    def key(self) -> str:
        """What its records say (``capture``); the full row's records have none."""
        return f"{self.steps}x{self.frequencies}"

    @property
    def name(self) -> str:
        return f"classical-{self.key}"


#: The capture curve: images per projector from the network's one to the full sequences (the
#: last is the classical row itself, tested)
CAPTURES = (
    # one image's views disagree more than the sequences' (its phase is filtered over a
    # period): its fusion keeps views within 0.3 mm of each other (0.1 mm cuts its coverage to
    # a quarter, 1 mm doubles its error; measured on training scenes of the tiny twin)
    Capture(1, 1, 0.3, 0.6),
    Capture(3),
    Capture(4),
    Capture(3, 2),
    Capture(4, 2),
    Capture(12),
    Capture(12, 2),
)


def capture_depth(stack, m, capture: Capture, camera, projectors, views) -> np.ndarray:
    """One scene's depth (mm, NaN where rejected) from ``capture``'s images of its full
    sequences (V, F, N, H, W in the manifest's frequency order)."""
    n_steps = m.fringe.steps
    if n_steps % capture.steps:
        raise DataError(f"classical: {capture.steps} steps do not divide the dataset's {n_steps}")
    f_net = m.fringe.resolve_frequency(m.fringe.train_frequency)
    coarse = int(np.argmax(m.fringe.periods_px))
    period, step0 = m.fringe.periods_px[f_net], m.fringe.train_step
    if capture.images == 1:
        return single_shot_depth(stack[:, f_net, step0], period, step0, n_steps, m.rig, views)
    picked = [(step0 + k * n_steps // capture.steps) % n_steps for k in range(capture.steps)]
    origin = 2 * np.pi * step0 / n_steps  # the steps picked start at step0: its phase offset
    ref = _reference_px(m.rig, views, stack.shape[-2:], period, step0, n_steps)
    depths, mods = [], []
    for v, proj in enumerate(projectors):
        if capture.frequencies == 2:
            periods = [m.fringe.periods_px[coarse], period]  # projector px
            images = stack[v][[coarse, f_net]][:, picked]
            u, mod, ok, _ = decode_phase(images, periods, MIN_MODULATION, 1, origin)
        else:
            phase, mod = wrapped_phase(stack[v, f_net][picked], 1, origin)
            u, ok = _anchored(phase - 2 * np.pi * ref[v] / period, mod, ref[v], period)
        depths.append(_triangulated(u, ok, camera, proj))
        mods.append(mod)
    return fuse_views(np.stack(depths), np.stack(mods), capture.tolerance_mm, capture.edge_mm)


def single_shot_depth(
    images: np.ndarray, period_px: float, step: int, n_steps: int, rig, views
) -> np.ndarray:
    """Depth (mm, NaN where rejected) from one fringe image per projector (V, H, W; linear
    intensity) of period ``period_px`` (projector px) at phase step ``step`` of ``n_steps``:
    Fourier-transform profilometry against the reference plane's carrier
    (:func:`odmv.classical.fringe.demodulate`), spatially unwrapped, the fringe order anchored
    to the plane, triangulated and fused as :data:`CAPTURES`' first row is."""
    capture = CAPTURES[0]
    h, w = images.shape[-2:]
    camera = rig.camera_at(w, h)
    ref = _reference_px(rig, views, (h, w), period_px, step, n_steps)
    depths, mods = [], []
    for v, name in enumerate(views):
        proj = rig.projectors()[name]
        carrier = 2 * np.pi * (ref[v] / period_px + step / n_steps)
        # the image axis the fringe's phase runs along
        axis = int(np.abs(np.diff(ref[v], axis=1)).mean() > np.abs(np.diff(ref[v], axis=0)).mean())
        period_camera = period_in_camera_px(period_px, camera, proj)
        dphi, mod = demodulate(images[v], carrier, period_camera, axis)
        u, ok = _anchored(dphi, mod, ref[v], period_px)
        depths.append(_triangulated(u, ok, camera, proj))
        mods.append(mod)
    return fuse_views(np.stack(depths), np.stack(mods), capture.tolerance_mm, capture.edge_mm)


def _reference_px(rig, views, size, period_px, step, n_steps) -> np.ndarray:
    """Each view's projector coordinate on the reference plane (V, H, W; projector px)."""
    maps = triangulation_maps(rig, views, *size, period_px, step, n_steps)
    return maps[:, 0].astype(np.float64)


def _anchored(dphi, mod, ref, period_px):
    """A phase difference to the plane (rad, wrapped) -> the projector coordinate (px), unwrapped
    spatially with its order anchored to the plane, and the pixels kept."""
    ok = mod >= MIN_MODULATION
    dphi = anchor_to_plane(unwrap_spatial(np.angle(np.exp(1j * dphi)), mod, ok), ok)
    u = ref + period_px * dphi / (2 * np.pi)
    return u, ok & np.isfinite(u)


def _triangulated(u, ok, camera, proj) -> np.ndarray:
    depth = triangulate_depth(np.nan_to_num(u), camera, proj)
    return np.where(ok & np.isfinite(depth), depth, np.nan)


def classical_row(
    root: str | Path,
    out_dir: str | Path,
    resolution=None,
    split: str = "test",
    capture: Capture | None = None,
) -> dict:
    """Reconstruct every scene of ``split`` of the dataset at ``root`` classically, from the
    images resized to ``resolution`` as the networks see them (None: as stored); write and
    return its metrics (keys like a trained run's: ``test/mae_mm``, ..., ``test/coverage``).
    ``capture``: the images decoded per projector (None: every step of every frequency the
    camera resolves)."""
    t0 = time.perf_counter()
    m = load_manifest(root)
    if m.images != "full":
        raise DataError(f"{m.root}: the classical row needs the full sequences (images=full)")
    size = [m.height_px, m.width_px] if resolution is None else resolution
    spec = check_spec(m, m.views, size, None, None, with_stacks=True)
    h, w = spec.height_px, spec.width_px
    ids = split_scenes(m, None, 0)[split]
    cam = m.rig.camera_at(w, h)
    projectors = [m.rig.projectors()[v] for v in m.views]
    n_f, n_s = len(m.fringe.periods_px), m.fringe.steps
    options = twin_options(m)
    coarse_first = np.argsort(m.fringe.periods_px)[::-1]
    families = {s["id"]: str(s.get("family", "")) for s in m.scenes}
    metrics = {k: DepthErrors() for k in SUBSETS}
    covered = {k: [0.0, 0.0] for k in SUBSETS}
    rows, preds = [], {"scene_id": [], "pred_mm": [], "depth_mm": []}
    for sid in ids:
        raw = load_scene(m, sid, spec)
        stack = raw["fringe_stack"].reshape(len(m.views), n_f, n_s, h, w)
        if capture is None:
            depth = reconstruct_scene(stack[:, coarse_first], cam, projectors, options)
        else:
            depth = capture_depth(stack, m, capture, cam, projectors, list(m.views))
        gt = torch.from_numpy(raw["depth_mm"][None].astype(np.float32))
        pred = torch.from_numpy(np.nan_to_num(depth, nan=0.0)[None, None].astype(np.float32))
        ok = torch.from_numpy(np.isfinite(depth)[None, None]).float()
        subsets = {k: torch.from_numpy(raw[k][None]).float() for k in MASKS}
        masks = subset_masks({"valid": torch.isfinite(gt).float(), "depth_mm": gt} | subsets)
        reconstructed = {k: mask * ok for k, mask in masks.items()}
        row = {"scene": sid, "family": families.get(sid, "")}
        for k, v in per_image_subset_errors(pred, gt, reconstructed).items():
            if not k.startswith("pixels"):
                row[k] = float(v[0])
        for subset, mask in masks.items():
            # each subset's pixels, as a trained run's file counts them (the report picks the
            # figures' scenes by them)
            row[f"pixels{subset_suffix(subset)}"] = float(mask.sum())
            metrics[subset].update(pred, gt, reconstructed[subset])
            covered[subset][0] += float(reconstructed[subset].sum())
            covered[subset][1] += float(mask.sum())
            row[f"coverage{subset_suffix(subset)}"] = float(reconstructed[subset].sum()) / max(
                float(mask.sum()), 1.0
            )
        rows.append(row)
        preds["scene_id"].append([sid])
        preds["pred_mm"].append(depth[None].astype(np.float32))
        preds["depth_mm"].append(raw["depth_mm"].astype(np.float32))
    if not ids:
        raise DataError(f"{m.root}: the {split} split is empty")
    out = {}
    valid_pixels = covered["all"][1]
    for subset in SUBSETS:
        suffix = subset_suffix(subset)
        for name, value in metrics[subset].compute().items():
            if name != "pixels":
                out[f"test/{name}{suffix}"] = float(value)
        out[f"test/coverage{suffix}"] = covered[subset][0] / max(covered[subset][1], 1.0)
        if subset != "all":
            out[f"test/share{suffix}"] = covered[subset][1] / max(valid_pixels, 1.0)
    out.update(
        model="classical",
        views=list(m.views),
        **({"capture": capture.key, "images_per_projector": capture.images} if capture else {}),
        parameters=0,
        train_seconds=0.0,
        test_seconds=round(time.perf_counter() - t0, 1),
        scenes=len(ids),
        resolution=[h, w],
        **provenance(m.root),
    )
    out_dir = Path(out_dir)
    write_test_outputs(out_dir, rows, preds)
    write_json(out_dir / METRICS, portable_record(out, out_dir))
    return out
