"""The one place where physical units meet network units.

Fringe images (linear intensity, 0 .. ``intensity_max``) map to [-1, 1] so the view
reconstruction head's Tanh can match them. Depth (mm, camera-axis z) maps to
``(depth_mm - center_mm) / half_range_mm``. Two targets (``for_working_distance``):
- ``depth`` (the default): the reference plane (the working distance) at +1 and objects up to
  2 * half_range_mm tall towards -1;
- ``height`` (beyond the paper): height above the reference plane, the plane at 0 and objects
  2 * half_range_mm tall at +2 (the same dynamic range, so SSIM's L stays 2). The scale is then
  negative: depth falls as height rises.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class Normalization:
    intensity_max: float = 1.0
    depth_center_mm: float = 140.0
    depth_half_range_mm: float = 10.0

    @classmethod
    def for_working_distance(
        cls,
        working_distance_mm: float,
        half_range_mm: float = 10.0,
        intensity_max: float = 1.0,
        target: str = "depth",
    ) -> Normalization:
        if target == "depth":
            return cls(intensity_max, working_distance_mm - half_range_mm, half_range_mm)
        if target == "height":
            return cls(intensity_max, working_distance_mm, -half_range_mm)
        raise ValueError(f"data.depth_target: {target!r} is not 'depth' or 'height'")

    @classmethod
    def for_depth_range(
        cls,
        lo_mm: float,
        hi_mm: float,
        intensity_max: float = 1.0,
        target: str = "depth",
        stored: str = "depth",
    ) -> Normalization:
        """For a dataset without a rig model (an import): its range [lo, hi] mm maps to
        [-1, 1]; as height, the farthest depth (``stored="height"``: the lowest height) is the
        plane at 0 and the nearest (the highest) is 2."""
        half = (hi_mm - lo_mm) / 2 * 1.05  # a margin for depths beyond the training range
        if target == "depth":
            return cls(intensity_max, (lo_mm + hi_mm) / 2, half)
        if target == "height":
            return (
                cls(intensity_max, lo_mm, half)
                if stored == "height"
                else cls(intensity_max, hi_mm, -half)
            )
        raise ValueError(f"data.depth_target: {target!r} is not 'depth' or 'height'")

    def fringes(self, images):
        """Linear intensity -> [-1, 1] (clipped at 0 and intensity_max)."""
        lib = torch if isinstance(images, torch.Tensor) else np
        return 2 * lib.clip(images / self.intensity_max, 0, 1) - 1

    def intensity(self, fringes):
        """[-1, 1] -> linear intensity (0 .. intensity_max): :meth:`fringes` undone."""
        return (fringes + 1) / 2 * self.intensity_max

    def depth(self, depth_mm):
        """mm -> network units."""
        return (depth_mm - self.depth_center_mm) / self.depth_half_range_mm

    def depth_mm(self, depth_norm):
        """Network units -> mm."""
        return depth_norm * self.depth_half_range_mm + self.depth_center_mm

    def to_dict(self) -> dict:
        return asdict(self)
