"""The absolute reference a calibrated rig has: the fringe phase of the reference plane.

A convolution sees the local phase of a fringe image but not which projector column a pixel
looks at, so a wide flat region has no absolute height except through its edges. A real rig
knows, from its calibration (or one capture of the flat reference plane), the phase each pixel
sees on the reference plane; the height of a surface point is encoded in the difference.
``reference`` (:func:`reference_mode`) gives each view three input channels:

- ``phase`` (or ``true``): the normalized fringe image I and sin / cos of the reference phase;
- ``demod``: I, I sin(phi_ref) and I cos(phi_ref), the fringe mixed down by the reference
  carrier as Fourier-transform profilometry does: with I = a + b cos(phi_ref + dphi), a local
  average over one period leaves (b/2) (-sin dphi, cos dphi), so the phase difference, i.e. the
  height, is a linear filter away instead of a product the net must learn to form.

Both are 0 outside the projector's footprint on the plane.
"""

from __future__ import annotations

import numpy as np
import torch

from odmv.rig import Rig

MODES = ("phase", "demod")


def reference_mode(value) -> str | None:
    """The reference setting as None (off), "phase" or "demod"; ``true`` means "phase"."""
    if value is None or value is False:
        return None
    if value is True:
        return "phase"
    if value in MODES:
        return value
    raise ValueError(f"reference: {value!r} unknown; choose false, true, phase or demod")


def view_channels(value) -> int:
    """Network input channels per view: the fringe alone, or three with the reference."""
    return 1 if reference_mode(value) is None else 3


def reference_phase(
    rig: Rig, views, height_px: int, width_px: int, period_px: float, step: int, n_steps: int
) -> np.ndarray:
    """(S, 2, H, W) float32: sin and cos of the phase of image ``step`` of the sequence with
    period ``period_px`` on the reference plane z = 0, at each pixel centre (0 outside the
    projector's footprint). Same convention as the renderer: 2 pi u / P + 2 pi n / N."""
    origin, d = rig.camera_at(width_px, height_px).centre_rays()
    pts = origin + (-origin[2] / d[..., 2])[..., None] * d
    projectors = rig.projectors()
    out = np.zeros((len(views), 2, height_px, width_px), np.float32)
    for k, v in enumerate(views):
        p = projectors[v]
        uv = p.project(pts)
        inside = p.in_image(uv)
        coord = uv[..., 0] if p.phase_axis == "u" else uv[..., 1]
        phase = 2 * np.pi * (coord / period_px + step / n_steps)
        out[k, 0] = np.where(inside, np.sin(phase), 0)
        out[k, 1] = np.where(inside, np.cos(phase), 0)
    return out


def network_input(
    fringes: torch.Tensor, reference: torch.Tensor | None, mode: str = "phase"
) -> torch.Tensor:
    """Normalized fringes (..., S, H, W) and reference (S, 2, H, W) or None -> the net's input
    (..., S * C, H, W), each view's channels together: (I, sin, cos) in ``phase`` mode,
    (I, I sin, I cos) in ``demod`` mode."""
    if reference is None:
        return fringes
    ref = reference.to(fringes).expand(*fringes.shape[:-3], *reference.shape)
    image = fringes.unsqueeze(-3)
    if mode == "demod":
        ref = image * ref
    stacked = torch.cat([image, ref], -3)  # ..., S, 3, H, W
    return stacked.flatten(-4, -3)
