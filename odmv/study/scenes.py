"""A scene as a result shows it (a page, the report's Fig. 6): its network images, ground
truth, each prediction, the subset of each pixel and the pixel's size on the base plane."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from odmv.data.dataset import DataError, check_spec, load_scene
from odmv.io.manifest import ManifestError, load_manifest

#: bits of a pixel's subset code: bit k lit by the dataset's view k (k < 5), then these
SHADOWED_BIT, NO_TRUTH_BIT = 1 << 5, 1 << 6


@dataclass
class Scene:
    """One scene as the page shows it; arrays H x W in mm (NaN: none)."""

    sid: str
    truth_mm: np.ndarray | None
    predictions: dict[str, np.ndarray]
    views: list[str] = field(default_factory=list)  # the dataset's, in its order
    fringes: dict[str, np.ndarray] = field(default_factory=dict)  # view -> network image
    subsets: np.ndarray | None = None  # H x W uint8 code (bits above)
    mm_per_px: float | None = None  # lateral size of a pixel on the base plane
    note: str = ""  # what is missing and why


def scene_inputs(dataset: Path, sid: str, shape: tuple[int, int]) -> Scene | None:
    """A dataset scene's network images, ground truth, subset codes and pixel size at
    ``shape`` (None when the dataset or scene is not on this machine)."""
    try:
        m = load_manifest(dataset)
        spec = check_spec(m, m.views, list(shape), None, None)
        s = load_scene(m, sid, spec)
    except (DataError, ManifestError, OSError, ValueError):
        return None
    truth = s["depth_mm"][0]
    code = np.zeros(shape, np.uint8)
    for k in range(len(m.views)):
        code |= s["lit"][k].astype(np.uint8) << k
    code |= s["shadowed"][0].astype(np.uint8) * SHADOWED_BIT
    code |= (~np.isfinite(truth)).astype(np.uint8) * NO_TRUTH_BIT
    mm_per_px = None
    if m.rig is not None:
        cam = m.rig.camera_at(shape[1], shape[0])
        mm_per_px = float(np.nanmedian(truth)) / float(cam.K[0, 0])
    return Scene(
        sid, truth, {}, list(m.views), dict(zip(m.views, s["fringes"], strict=True)), code,
        mm_per_px,
    )  # fmt: skip
