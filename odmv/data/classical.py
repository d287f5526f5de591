"""A dataset's scenes reconstructed by phase shifting from their full sequences, at a net's
size: the classical target that label-free adaptation trains on, and each projector's
deviation from the others that its calibration check reads. Reads no labels: a user's captures
will do."""

from __future__ import annotations

import numpy as np

from odmv.classical.fringe import view_deviations_mm
from odmv.classical.reconstruct import decode_views, fused_views, twin_options, view_depths
from odmv.data.dataset import DataError, load_stack
from odmv.io.manifest import Manifest


def classical_depths(
    m: Manifest, ids: list[str], size: tuple[int, int]
) -> tuple[dict, dict[str, float]]:
    """Each scene of ``ids`` of the dataset of manifest ``m`` (with its full sequences)
    reconstructed classically from its images resized to ``size`` (H, W) -> {scene id: depth
    (mm, H x W, NaN where nothing is reconstructed)}, and each projector's mean deviation (mm)
    from the views' per-pixel median over those scenes (:func:`view_deviations_mm`; by view,
    those that share pixels with another): a calibration that describes the rig leaves them
    near zero whatever the optics, a projector moved since calibrating shifts its own."""
    if m.images != "full":
        raise DataError(
            f"{m.root}: the classical reconstruction needs the full phase-shifting sequences "
            f"(images=full), not images={m.images}"
        )
    h, w = size
    cam = m.rig.camera_at(w, h)
    projectors = [m.rig.projectors()[v] for v in m.views]
    n_f, n_s = len(m.fringe.periods_px), m.fringe.steps
    coarse_first = np.argsort(m.fringe.periods_px)[::-1]
    options = twin_options(m)
    depths, sums, counts = {}, np.zeros(len(m.views)), np.zeros(len(m.views))
    for sid in ids:
        stack = load_stack(m, sid, m.views, h, w).reshape(len(m.views), n_f, n_s, h, w)
        decoded = decode_views(stack[:, coarse_first], options, cam, projectors)
        per_view = view_depths(decoded, cam, projectors)
        depths[sid] = fused_views(decoded, per_view)
        s, c = view_deviations_mm(per_view)
        sums, counts = sums + s, counts + c
    offsets = {v: float(s / c) for v, s, c in zip(m.views, sums, counts, strict=True) if c}
    return depths, offsets
