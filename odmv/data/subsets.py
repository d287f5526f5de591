"""Pixel subsets for metrics, from the ground truth of every projector of the dataset.

They never depend on which views a model sees, so every model is scored on the same pixels:

- ``all``: valid pixels (finite depth);
- ``shadowed``: inside at least one projector's footprint (its frustum) but unlit by at least one
  projector whose footprint covers it, because something blocks its light or the surface faces
  away: where occlusion handling matters;
- ``unlit``: lit by no projector (e.g. image corners outside every footprint, or a pit shadowed
  from all sides);
- ``first_unlit``: unlit by the dataset's first projector (``right``, the one a single-view model
  sees) but lit by another: where one view has no fringe and more views do. On the paper's rig
  most of it lies outside the first projector's footprint (a 23 mm band of the 35.5 mm field);
- ``first_shadowed``: the part of ``first_unlit`` inside the first projector's footprint: what
  occlusion hides from the one view.

The metrics' edge band (:func:`edge_band`) comes from the depth alone: the pixels within 1 px
of a jump over 1 mm between neighbours, where a pixel mixes two surfaces and a net's error is
mostly where it places the edge.

``shadowed`` and ``unlit`` may overlap (a pixel in one footprint, shadowed there, outside the
others). The footprint comes from ``footprint.exr`` where the dataset has it; otherwise it is
computed from the depth map and the manifest's rig (:func:`footprint_from_depth`), which is exact
when the rig is, and as good as the calibration for imported data.
"""

from __future__ import annotations

import numpy as np
import torch

from odmv.rig import Rig

#: a depth jump: neighbouring pixels whose ground-truth depths differ by more than this (mm)
EDGE_JUMP_MM = 1.0
#: pixels within this many px (in x and y) of a jump pixel are the metrics' edge band
EDGE_RADIUS_PX = 1

#: the masks :func:`subset_masks` returns, each (1, H, W) per scene
MASKS = ("shadowed", "unlit", "first_unlit", "first_shadowed")


def footprint_from_depth(rig: Rig, depth_mm: np.ndarray, views) -> np.ndarray:
    """(V, H, W) bool: whether each pixel's surface point lies inside each projector's frustum.

    The point is the pixel-centre ray (distortion inverted) at the ground-truth depth."""
    h, w = depth_mm.shape
    cam = rig.camera_at(w, h)
    origin, d = cam.centre_rays()
    t = (depth_mm.astype(np.float64) - cam.depth(origin)) / (d @ cam.R[2])
    pts = origin + t[..., None] * d
    projectors = rig.projectors()
    out = []
    for v in views:
        p = projectors[v]
        z = (pts @ p.R.T + p.t)[..., 2]
        out.append((z > 0) & p.in_image(p.project(pts)))
    return np.stack(out)


def subset_masks(lit: np.ndarray, footprint: np.ndarray) -> dict[str, np.ndarray]:
    """``lit`` and ``footprint`` (V, H, W) bool over all projectors -> (1, H, W) bool masks
    ``shadowed``, ``unlit``, ``first_unlit`` and ``first_shadowed`` (``all`` is the valid mask,
    not needed here)."""
    lit, footprint = lit.astype(bool), footprint.astype(bool)
    return {
        "shadowed": (footprint & ~lit).any(0)[None],
        "unlit": ~lit.any(0)[None],
    } | first_view_subsets(lit, footprint)


def first_view_subsets(lit, footprint) -> dict:
    """``first_unlit`` and ``first_shadowed`` (1, H, W) bool from ``lit`` and ``footprint``
    (V, H, W) bool over all projectors, the first projector first (numpy or torch)."""
    hidden = ~lit[0] & lit[1:].any(0)
    return {"first_unlit": hidden[None], "first_shadowed": (hidden & footprint[0])[None]}


def edge_band(depth_mm: torch.Tensor, radius_px: int = EDGE_RADIUS_PX) -> torch.Tensor:
    """B x 1 x H x W bool: the pixels within ``radius_px`` (in x and y) of a depth jump, i.e. of a
    pixel whose depth (mm; NaN: none, never a jump) differs from a 4-neighbour's by more than
    :data:`EDGE_JUMP_MM` (both pixels of the pair are jump pixels)."""
    jump = torch.zeros_like(depth_mm, dtype=torch.bool)
    dx = (depth_mm[..., :, 1:] - depth_mm[..., :, :-1]).abs() > EDGE_JUMP_MM
    dy = (depth_mm[..., 1:, :] - depth_mm[..., :-1, :]).abs() > EDGE_JUMP_MM
    jump[..., :, 1:] |= dx
    jump[..., :, :-1] |= dx
    jump[..., 1:, :] |= dy
    jump[..., :-1, :] |= dy
    k = 2 * radius_px + 1
    return torch.nn.functional.max_pool2d(jump.float(), k, 1, radius_px) > 0
