"""The rig's triangulation as per-pixel maps, and in torch: projector offset -> depth.

A camera pixel looks along one ray; a projector's fringe labels every point of it with a
coordinate ``u`` along the projector's phase axis (odmv.rig). On the reference plane the pixel
sees ``u_ref``; a surface above or below the plane moves it by the offset ``delta = u - u_ref``
(projector px). Along the pixel's ray the depth is a Moebius function of that offset,

    depth = d_ref + delta * g / (1 - delta * h),

with ``d_ref`` the reference plane's depth at the pixel and ``g`` (mm / px), ``h`` (1 / px) from
the calibration: exactly the plane-ray intersection of
:func:`odmv.classical.fringe.triangulate_depth`,
rewritten around the plane so that float32 keeps it to 1e-5 mm (``u`` itself is ~1e3 px, and the
intersection's terms cancel). The maps are computed once per rig, view, image size and fringe
(float64, then float32) and travel with every sample, so a net with a phase head turns phase
into depth through whatever rig its data came from.

The phase of a fringe image (period ``P`` projector px, phase step ``n`` of ``N``) at a pixel is
2 pi (u / P + n / N), so a wrapped phase gives the offset up to whole periods:
delta / P = phase / 2 pi - n / N - u_ref / P + k. The fringe order k relative to the plane is
what the wrapped phase cannot tell (:func:`offset_from_phase`).
"""

from __future__ import annotations

import numpy as np
import torch

from odmv.rig import Camera, Projector

#: Channels of a view's triangulation maps, in order.
CHANNELS = (
    "ref_coord_px",
    "period_px",
    "step_cycles",
    "gain_mm_per_px",
    "pole_per_px",
    "ref_depth_mm",
)


def _view_maps(camera: Camera, proj: Projector, period_px: float, phase0: float) -> np.ndarray:
    origin, d = camera.centre_rays()  # H x W x 3 unit rays from the camera centre
    # the reference plane z = 0 along each ray
    ref = origin + (-origin[2] / d[..., 2])[..., None] * d
    uv = proj.project(ref)
    row = 0 if proj.phase_axis == "u" else 1
    u_ref = uv[..., row]
    P = proj.P
    # plane of constant u: (P_row - u P_2) . [X, 1] = 0; along the ray X = o + t d:
    # t(u) = -(a1 - u a2) / (b1 - u b2), depth = t dz
    a1, a2 = P[row, :3] @ origin + P[row, 3], P[2, :3] @ origin + P[2, 3]
    b1, b2 = d @ P[row, :3], d @ P[2, :3]
    dz = d @ camera.R[2]
    n0, d0 = a1 - u_ref * a2, b1 - u_ref * b2
    ref_depth = -dz * n0 / d0
    gain = -dz * (n0 * b2 - a2 * d0) / d0**2
    pole = b2 / d0
    return np.stack(
        [u_ref, np.full_like(u_ref, period_px), np.full_like(u_ref, phase0), gain, pole, ref_depth]
    )


def triangulation_maps(
    rig, views, height_px: int, width_px: int, period_px: float, step: int = 0, n_steps: int = 1
) -> np.ndarray:
    """(S, 6, H, W) float32 maps of :data:`CHANNELS` for the fringe image of period
    ``period_px`` (projector px) and phase step ``step`` of ``n_steps``, at every pixel centre
    of an ``height_px`` x ``width_px`` image of ``rig`` (a :class:`odmv.rig.Rig` or a
    calibration file's rig)."""
    camera = rig.camera_at(width_px, height_px)
    projectors = rig.projectors()
    return np.stack(
        [_view_maps(camera, projectors[v], period_px, step / n_steps) for v in views]
    ).astype(np.float32)


def depth_from_offset(delta_px: torch.Tensor, maps: torch.Tensor) -> torch.Tensor:
    """Projector offsets from the reference plane (B x S x H x W, px) -> depth (mm), through
    the maps (B x S x 6 x H x W); differentiable."""
    gain, pole, ref_depth = maps[:, :, 3], maps[:, :, 4], maps[:, :, 5]
    return ref_depth + delta_px * gain / (1 - delta_px * pole)


def offset_from_depth(depth_mm: torch.Tensor, maps: torch.Tensor) -> torch.Tensor:
    """Depth (B x 1 x H x W, mm) -> each view's offset from the reference plane (B x S x H x
    W, px): :func:`depth_from_offset` inverted."""
    rise = depth_mm - maps[:, :, 5]
    return rise / (maps[:, :, 3] + rise * maps[:, :, 4])


def coord_from_depth(depth_mm: torch.Tensor, maps: torch.Tensor) -> torch.Tensor:
    """Depth (B x 1 x H x W, mm) -> the projector coordinate each view's projector casts on
    the surface point every pixel sees (B x S x H x W, projector px along its phase axis): the
    simulator's projection of the point into the projector, differentiable in the depth."""
    return maps[:, :, 0] + offset_from_depth(depth_mm, maps)


def phase_from_depth(depth_mm: torch.Tensor, maps: torch.Tensor) -> torch.Tensor:
    """Depth (B x 1 x H x W, mm) -> the phase (rad, unwrapped) of each view's input fringe
    image at every pixel, 2 pi (u / P + n / N): what the image would carry if the depth were
    right."""
    return 2 * torch.pi * (coord_from_depth(depth_mm, maps) / maps[:, :, 1] + maps[:, :, 2])


def offset_from_coord(coord_px: torch.Tensor, maps: torch.Tensor) -> torch.Tensor:
    """Projector coordinates (B x S x H x W, px; NaN where unlit) -> offsets from the reference
    plane (px)."""
    return coord_px - maps[:, :, 0]


def fraction_from_phase(sin_cos: torch.Tensor, maps: torch.Tensor) -> torch.Tensor:
    """A fringe image's wrapped phase as (sin, cos) (B x S x 2 x H x W) -> the offset's
    fractional part in periods, in [0, 1): delta / P minus its order. Differentiable (the
    wrap only adds whole periods)."""
    cycles = torch.atan2(sin_cos[:, :, 0], sin_cos[:, :, 1]) / (2 * torch.pi)
    return torch.remainder(cycles - maps[:, :, 2] - maps[:, :, 0] / maps[:, :, 1], 1.0)


def offset_from_phase(fraction: torch.Tensor, coarse: torch.Tensor, maps: torch.Tensor):
    """The offset (px) from its fractional part (periods, :func:`fraction_from_phase`) and a
    coarse estimate of it (periods, e.g. from a coarser depth): the order is
    the whole number that brings the fine estimate nearest the coarse one, so the coarse one
    need only be right to half a period, and the fine phase sets every digit below that (as
    temporal unwrapping does with a coarse fringe). The order carries no gradient."""
    order = torch.round(coarse.detach() - fraction.detach())
    return maps[:, :, 1] * (order + fraction)
