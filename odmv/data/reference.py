"""The absolute reference a calibrated rig has: the fringe phase of the reference plane.

A convolution sees the local phase of a fringe image but not which projector column a pixel
looks at, so a wide flat region has no absolute height except through its edges. A real rig
knows, from its calibration (or one capture of the flat reference plane), the phase each pixel
sees on the reference plane; the height of a surface point is encoded in the difference. With
``reference`` on, each view's network input is three channels: the normalized fringe image and
sin / cos of that reference phase (0 outside the projector's footprint on the plane).
"""

from __future__ import annotations

import numpy as np
import torch

from odmv.rig import Rig

#: Network input channels per view: the fringe, and with the reference its sin and cos.
CHANNELS = {False: 1, True: 3}


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
        phase = 2 * np.pi * (uv[..., 0] / period_px + step / n_steps)
        out[k, 0] = np.where(inside, np.sin(phase), 0)
        out[k, 1] = np.where(inside, np.cos(phase), 0)
    return out


def network_input(fringes: torch.Tensor, reference: torch.Tensor | None) -> torch.Tensor:
    """Normalized fringes (..., S, H, W) and reference (S, 2, H, W) or None -> the net's input
    (..., S * C, H, W), each view's channels together (fringe, sin, cos)."""
    if reference is None:
        return fringes
    ref = reference.to(fringes).expand(*fringes.shape[:-3], *reference.shape)
    stacked = torch.cat([fringes.unsqueeze(-3), ref], -3)  # ..., S, 3, H, W
    return stacked.flatten(-4, -3)
