"""The classical pipeline on one scene's images, without a net: phase shifting on every
projector, triangulation, fusion over the projectors that lit each pixel
(odmv.classical.fringe); and with fewer images per projector, down to the one image a network
sees (single-shot Fourier-transform profilometry), as a :class:`Capture` says
(:data:`CAPTURES`). A dataset's scenes reconstructed: odmv.data.classical; scored as a model
row: odmv.study.classical."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from odmv.classical.fringe import (
    anchor_to_plane,
    decode_phase,
    demodulate,
    fuse_views,
    period_in_camera_px,
    triangulate_depth,
    unwrap_spatial,
    wrapped_phase,
)
from odmv.classical.geometry import triangulation_maps
from odmv.classical.sequences import PspOptions, SequenceError

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
        raise SequenceError(
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
    return fused_views(decoded, view_depths(decoded, camera, projectors))


def fused_views(decoded: list[DecodedView], depths: np.ndarray) -> np.ndarray:
    """The views' triangulated ``depths`` (:func:`view_depths`) fused over those that agree."""
    modulations = np.stack([view.modulation for view in decoded])
    return fuse_views(depths, modulations, TOLERANCE_MM, EDGE_MM)


def reconstruct_scene(stack: np.ndarray, camera, projectors, options: PspOptions) -> np.ndarray:
    """Full sequences (V, F, N, H, W; frequencies in the order of ``options.frequencies``) of
    the projectors ``projectors`` (a list) -> depth (mm, NaN where rejected), using the
    sequences whose period the camera resolves."""
    return fused_depth(decode_views(stack, options, camera, projectors), camera, projectors)


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
        raise SequenceError(
            f"classical: {capture.steps} steps do not divide the dataset's {n_steps}"
        )
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
