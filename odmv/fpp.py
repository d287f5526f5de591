"""Classical fringe analysis: N-step phase shifting, temporal unwrapping, triangulation.

The reference that learned methods are measured against, and the check that the digital twin's
images and calibration agree: rendered fringes -> phase -> projector column -> depth in mm.
Conventions follow the renderer: image n of an N-step sequence is A + B cos(phi + 2 pi n / N)
with phi = 2 pi u / P, u the projector column (px) and P the period (px).
"""

from __future__ import annotations

import numpy as np

from odmv.rig import Camera, Projector


def wrapped_phase(images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """N-step phase shifting: images (N, H, W) -> (phase in [0, 2 pi), modulation B).

    Least-squares phase for shifts 2 pi n / N; the modulation tells how reliable it is.
    """
    n = images.shape[0]
    delta = 2 * np.pi * np.arange(n) / n
    s = np.tensordot(np.sin(delta), images, 1)
    c = np.tensordot(np.cos(delta), images, 1)
    phase = np.mod(np.arctan2(-s, c), 2 * np.pi)
    return phase, 2 / n * np.hypot(s, c)


def unwrap_temporal(phases: list[np.ndarray], periods_px: list[float]) -> np.ndarray:
    """Hierarchical temporal unwrapping -> projector column u (px) of the finest sequence.

    ``phases`` are wrapped phases ordered like ``periods_px``; the coarsest period must span
    the projector (one period across it), so its phase is already absolute.
    """
    order = np.argsort(periods_px)[::-1]  # coarse to fine
    u = phases[order[0]] / (2 * np.pi) * periods_px[order[0]]
    for i in order[1:]:
        p = periods_px[i]
        k = np.round((2 * np.pi * u / p - phases[i]) / (2 * np.pi))
        u = (phases[i] + 2 * np.pi * k) / (2 * np.pi) * p
    return u


def triangulate_depth(u_px: np.ndarray, camera: Camera, projector: Projector) -> np.ndarray:
    """Depth (camera-axis z, mm) of each camera pixel from its projector column ``u_px`` (H, W).

    Intersects the pixel-centre ray (lens distortion inverted) with the projector plane of
    constant column u: (P_row0 - u P_row2) . [X, 1] = 0.
    """
    h, w = u_px.shape
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    origin, d = camera.pixel_rays(np.stack([jj, ii], -1))
    P = projector.P
    a = P[0, :3] - u_px[..., None] * P[2, :3]
    b = P[0, 3] - u_px * P[2, 3]
    t = -(a @ origin + b) / (a * d).sum(-1)
    return camera.depth(origin + t[..., None] * d)
