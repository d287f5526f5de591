"""How far a prior gets on a dataset: what a net could recall instead of measure.

On the fixed twin every background lies at one depth (the base plane; a pcb board's top 1.6 mm
above it), so the best constant per scene family already predicts the flat pixels to a small
error, and a net that remembers the plane beats one that measures there. A dataset of scenes
that move (``pose=random``) must make that constant poor: :func:`prior_summary` gives the spread
of the background's depth over the dataset and the MAE of the best constant per family on flat
pixels, printed by ``odmv.simulate`` after every render.
"""

from __future__ import annotations

import numpy as np
import torch

from odmv.data.subsets import edge_band
from odmv.io.exr import read_exr
from odmv.io.manifest import DEPTH_CHANNEL, DEPTH_FILE, Manifest

#: flat pixels lie at least this far (px, in x and y) from any depth jump
FLAT_MARGIN_PX = 3
#: depth maps are read at most this size (every k-th pixel): a summary, not a metric
SUMMARY_PX = 128


def flat_depths(depth_mm: np.ndarray) -> np.ndarray:
    """The depths (mm) of the flat pixels of one depth map: finite, and more than
    :data:`FLAT_MARGIN_PX` from a depth jump."""
    step = max(1, max(depth_mm.shape) // SUMMARY_PX)
    d = torch.from_numpy(np.ascontiguousarray(depth_mm[::step, ::step], np.float32))[None, None]
    near_edge = edge_band(d, max(1, FLAT_MARGIN_PX // step))[0, 0].numpy()
    v = d[0, 0].numpy()
    return v[np.isfinite(v) & ~near_edge]


def prior_summary(m: Manifest) -> dict:
    """``background_mm``: the median depth of each scene's flat pixels (its background, which
    covers most of them), over the dataset: mean, std, min, max; ``constant_mae_mm``: per
    family, the MAE of the best constant (the median) on every flat pixel of its scenes."""
    per_family: dict[str, list[np.ndarray]] = {}
    backgrounds = []
    for s in m.scenes:
        path = m.scene_dir(s["id"]) / DEPTH_FILE
        flat = flat_depths(read_exr(path)[DEPTH_CHANNEL])
        if not flat.size:
            continue
        backgrounds.append(float(np.median(flat)))
        per_family.setdefault(str(s.get("family", "")), []).append(flat)
    b = np.array(backgrounds)
    constant = {}
    for fam, parts in sorted(per_family.items()):
        d = np.concatenate(parts)
        constant[fam] = float(np.abs(d - np.median(d)).mean())
    stats = {"mean": np.mean, "std": np.std, "min": np.min, "max": np.max}
    return {
        "background_mm": {k: float(f(b)) if b.size else float("nan") for k, f in stats.items()},
        "constant_mae_mm": constant,
    }


def summary_lines(summary: dict) -> list[str]:
    b = summary["background_mm"]
    fams = ", ".join(f"{k} {v:.3f} mm" for k, v in summary["constant_mae_mm"].items())
    return [
        f"background depth over the dataset: {b['mean']:.2f} ± {b['std']:.2f} mm "
        f"(from {b['min']:.2f} to {b['max']:.2f})",
        f"best constant per family on flat pixels: MAE {fams}",
    ]
