"""Classical fringe analysis: N-step phase shifting, single-shot Fourier-transform
profilometry, temporal and spatial unwrapping, triangulation.

The reference that learned methods are measured against, and the check that the digital twin's
images and calibration agree: rendered fringes -> phase -> projector column -> depth in mm.
Conventions follow the renderer: image n of an N-step sequence is A + B cos(phi + 2 pi n / N)
with phi = 2 pi u / P, u the projector coordinate along its phase axis (px) and P the period
(px). Real sequences may shift the other way or start elsewhere (``shift_sign``,
``phase_origin_rad``).
"""

from __future__ import annotations

import heapq
import warnings

import numpy as np

from odmv.rig import Camera, Projector


def wrapped_phase(
    images: np.ndarray, shift_sign: int = 1, phase_origin_rad: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """N-step phase shifting: images (N, H, W) -> (phase in [0, 2 pi), modulation B).

    Least-squares phase for image n = A + B cos(phi + shift_sign 2 pi n / N + phase_origin_rad);
    the modulation tells how reliable it is.
    """
    n = images.shape[0]
    delta = shift_sign * 2 * np.pi * np.arange(n) / n + phase_origin_rad
    s = np.tensordot(np.sin(delta), images, 1)
    c = np.tensordot(np.cos(delta), images, 1)
    phase = np.mod(np.arctan2(-s, c), 2 * np.pi)
    return phase, 2 / n * np.hypot(s, c)


def unwrap_temporal(phases: list[np.ndarray], periods_px: list[float]) -> np.ndarray:
    """Hierarchical temporal unwrapping -> projector column u (px) of the finest sequence.

    ``phases`` are wrapped phases ordered like ``periods_px``; the coarsest period must span
    the projector (one period across it), so its phase is already absolute.
    """
    return unwrap_checked(phases, periods_px)[0]


def unwrap_checked(
    phases: list[np.ndarray], periods_px: list[float]
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`unwrap_temporal`, and where every pair of consecutive levels agreed within a
    quarter of the finer period (elsewhere a fringe order is wrong, typically at mixed pixels
    on edges)."""
    order = np.argsort(periods_px)[::-1]  # coarse to fine
    u = phases[order[0]] / (2 * np.pi) * periods_px[order[0]]
    agree = np.ones(np.shape(u), bool)
    for i in order[1:]:
        p = periods_px[i]
        k = np.round((2 * np.pi * u / p - phases[i]) / (2 * np.pi))
        fine = (phases[i] + 2 * np.pi * k) / (2 * np.pi) * p
        agree &= np.abs(fine - u) < p / 4
        u = fine
    return u, agree


def unwrap_spatial(phase: np.ndarray, quality: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Quality-guided spatial unwrapping of a wrapped phase (H, W) over the pixels ``ok``.

    Each 4-connected region of ``ok`` grows from its best pixel (highest ``quality``, e.g. the
    modulation), always to the best neighbour of what is unwrapped, adding to each pixel the
    multiple of 2 pi that brings it nearest its unwrapped neighbour; the seed keeps its wrapped
    value. So the result is relative: each region is off the absolute phase by an unknown
    multiple of 2 pi, and a step of more than pi between neighbours unwraps wrongly. NaN
    outside ``ok``."""
    h, w = phase.shape
    out = np.full((h, w), np.nan)
    done = ~ok.copy()
    q = np.where(ok, quality, -np.inf).ravel()
    for seed in np.argsort(-q):
        if done.flat[seed]:
            continue
        if not np.isfinite(q[seed]):
            break
        out.flat[seed] = phase.flat[seed]
        done.flat[seed] = True
        heap = [(-q[seed], int(seed))]
        while heap:
            _, i = heapq.heappop(heap)
            r, c = divmod(i, w)
            for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
                if 0 <= rr < h and 0 <= cc < w and not done[rr, cc]:
                    j = rr * w + cc
                    step = phase.flat[j] - out.flat[i]
                    out.flat[j] = phase.flat[j] - 2 * np.pi * np.round(step / (2 * np.pi))
                    done.flat[j] = True
                    heapq.heappush(heap, (-q[j], j))
    return out


def decode_phase(
    stack: np.ndarray,
    periods: list[float],
    min_modulation: float,
    shift_sign: int = 1,
    phase_origin_rad: float = 0.0,
    unwrap: str = "temporal",
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One projector's sequences (F, N, H, W; linear intensity) -> the unwrapped coordinate
    along its phase axis (in the unit of ``periods``: give projector px and it is px), the
    modulation of the finest sequence, the pixels kept, and the pixels where every sequence is
    modulated (over which the kept share tells whether the conventions are right).

    Kept: modulation at least ``min_modulation`` in every sequence (elsewhere unlit, shadowed,
    or a mixed pixel whose surfaces cancel) and consecutive unwrapping levels that agree within
    a quarter of the finer period (elsewhere a fringe order is wrong: a mixed pixel at an edge,
    or, on most pixels, a sequence read with the wrong conventions). ``unwrap="spatial"``
    unwraps the coarsest sequence spatially (:func:`unwrap_spatial`), so the coordinate is
    relative: off by an unknown whole number of coarsest periods per connected region."""
    phases, mods = zip(
        *(wrapped_phase(s, shift_sign, phase_origin_rad) for s in stack), strict=True
    )
    modulated = np.logical_and.reduce([m >= min_modulation for m in mods])
    phases = list(phases)
    coarsest = int(np.argmax(periods))
    if unwrap == "spatial":
        phases[coarsest] = unwrap_spatial(phases[coarsest], mods[coarsest], modulated)
    elif unwrap != "temporal":
        raise ValueError(f"unwrap: {unwrap!r} unknown; choose temporal or spatial")
    u, ok = unwrap_checked(phases, periods)
    return u, mods[int(np.argmin(periods))], ok & modulated & np.isfinite(u), modulated


def demodulate(
    image: np.ndarray, reference_rad: np.ndarray, period_px: float, axis: int
) -> tuple[np.ndarray, np.ndarray]:
    """Single-shot Fourier-transform profilometry of one fringe image (H, W; linear intensity)
    against the phase the reference plane gives each pixel (``reference_rad``, H x W) ->
    (the phase difference in (-pi, pi], the modulation B).

    The image I = A + B cos(phi) is mixed down by the reference carrier: I exp(-i phi_ref)
    = (B / 2) exp(i (phi - phi_ref)) + A exp(-i phi_ref) + (B / 2) exp(-i (phi + phi_ref)).
    A moving average over one fringe period (``period_px``, camera px, along image ``axis``:
    1 for fringes whose phase runs along the columns) removes the two carrier terms, at one and
    two periods, exactly for a uniform carrier, and leaves the height-induced phase at the
    resolution of one period: the filter that carrier filtering in the Fourier domain is."""
    mixed = image * np.exp(-1j * reference_rad)
    return _period_mean(mixed, period_px, axis)


def _period_mean(z: np.ndarray, period_px: float, axis: int) -> tuple[np.ndarray, np.ndarray]:
    from scipy.ndimage import convolve1d

    n = int(np.ceil(period_px))
    n += 1 - n % 2  # odd, centred
    k = np.ones(n)
    k[[0, -1]] = 1 - (n - period_px) / 2  # fractional ends: the box is one period long
    k /= k.sum()
    low = convolve1d(z.real, k, axis=axis, mode="nearest") + 1j * convolve1d(
        z.imag, k, axis=axis, mode="nearest"
    )
    return np.angle(low), 2 * np.abs(low)


def anchor_to_plane(offset_rad: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """A spatially unwrapped phase difference to the reference plane (H, W; each 4-connected
    region of ``ok`` off by an unknown multiple of 2 pi, :func:`unwrap_spatial`) with each
    region's multiple chosen so that its median lies nearest the plane (within pi): the fringe
    order a single image cannot tell, guessed as the twin's scenes have it (most of each
    region on or near the base plane). A region wholly on a part taller than half a fringe
    period is placed a period low."""
    from scipy.ndimage import label

    regions, n = label(ok)
    out = offset_rad.copy()
    for r in range(1, n + 1):
        sel = regions == r
        out[sel] -= 2 * np.pi * np.round(np.median(offset_rad[sel]) / (2 * np.pi))
    return out


def triangulate_depth(u_px: np.ndarray, camera: Camera, projector: Projector) -> np.ndarray:
    """Depth (camera-axis z, mm) of each camera pixel from its projector coordinate ``u_px``
    (H, W) along the projector's phase axis (its column u, or its row v).

    Intersects the pixel-centre ray (lens distortion inverted) with the projector plane of
    constant coordinate u: (P_axis - u P_row2) . [X, 1] = 0.
    """
    origin, d = camera.centre_rays()
    P = projector.P
    row = 0 if projector.phase_axis == "u" else 1
    a = P[row, :3] - u_px[..., None] * P[2, :3]
    b = P[row, 3] - u_px * P[2, 3]
    t = -(a @ origin + b) / (a * d).sum(-1)
    return camera.depth(origin + t[..., None] * d)


def period_in_camera_px(period_px: float, camera: Camera, projector: Projector) -> float:
    """A fringe period (projector px) as the camera sees it on the reference plane (camera px),
    at the projector's principal point: tells which sequences the camera resolves."""
    cx, cy = projector.K[0, 2], projector.K[1, 2]
    step = [period_px, 0.0] if projector.phase_axis == "u" else [0.0, period_px]
    origin, d = projector.rays(np.array([[cx, cy], [cx + step[0], cy + step[1]]]))
    pts = origin + (-origin[2] / d[:, 2])[:, None] * d
    uv = camera.project(pts)
    return float(np.linalg.norm(uv[1] - uv[0]))


def _nanmedian(a: np.ndarray) -> np.ndarray:
    """Median over axis 0 ignoring NaN; NaN (without a warning) where all are NaN."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(a, 0)


def view_deviations_mm(depths: np.ndarray, clip_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-projector depths (V, H, W; NaN = none) -> each view's summed deviation (mm) from
    the per-pixel median of the views, over the pixels it shares with at least one other
    view, each deviation clipped to +-``clip_mm`` (a wrong fringe order is millimetres off: a
    few must not outweigh the rest); and those pixels' counts (V each)."""
    seen = np.isfinite(depths)
    shared = seen & (seen.sum(0) >= 2)
    deviation = np.clip(np.nan_to_num(depths - _nanmedian(depths)), -clip_mm, clip_mm)
    return np.where(shared, deviation, 0.0).sum((1, 2)), shared.sum((1, 2)).astype(np.float64)


def fuse_views(
    depths: np.ndarray, modulations: np.ndarray, tolerance_mm: float, edge_mm: float
) -> np.ndarray:
    """Per-projector depths (V, H, W; NaN = none) -> one depth map (NaN where rejected).

    Views within ``tolerance_mm`` of the per-pixel median are averaged with weights B**2 (the
    phase variance of N-step shifting falls as 1 / B**2); a pixel where no majority of its views
    agrees (e.g. two views that disagree: nothing says which is right) is rejected. Then pixels
    that differ from the median of their 3 x 3 neighbourhood by more than ``edge_mm`` (mixed
    pixels at depth edges, flying pixels) are rejected."""
    seen = np.isfinite(depths)
    agree = seen & (
        np.abs(np.nan_to_num(depths) - np.nan_to_num(_nanmedian(depths))) <= tolerance_mm
    )
    w = np.where(agree, modulations.astype(np.float64) ** 2, 0.0)
    total = w.sum(0)
    fused = np.full(depths.shape[1:], np.nan)
    ok = total > 0
    fused[ok] = (np.nan_to_num(depths) * w).sum(0)[ok] / total[ok]
    fused[2 * agree.sum(0) <= seen.sum(0)] = np.nan  # no majority agrees
    h, wd = fused.shape
    padded = np.pad(fused, 1, mode="edge")
    local = _nanmedian(
        np.stack([padded[i : i + h, j : j + wd] for i in range(3) for j in range(3)])
    )
    fused[np.abs(fused - local) > edge_mm] = np.nan
    return fused
