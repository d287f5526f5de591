"""The classical reference as a model row: the test scenes reconstructed without a net
(odmv.classical.reconstruct), scored like a network.

``classical_row(root, out_dir)`` reads the full sequences of the test scenes, writes the same
files a trained run's test writes (``metrics.json``, ``test_scenes.csv``,
``test_predictions.npz``; NaN where nothing is reconstructed) and returns the metrics. Errors are
over the reconstructed pixels of each subset; ``coverage`` is the share of the subset's valid
pixels that is reconstructed. A :class:`~odmv.classical.reconstruct.Capture` makes the row see
fewer images per projector, down to the one image a network sees: what learning adds is
measured against what the classical method does with the same images.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from odmv.classical.reconstruct import Capture, capture_depth, reconstruct_scene, twin_options
from odmv.data.dataset import DataError, check_spec, load_scene, split_scenes
from odmv.data.subsets import MASKS
from odmv.io.atomic import write_json
from odmv.io.manifest import load_manifest
from odmv.io.runfolder import METRICS, portable_record
from odmv.training.metrics import SUBSETS, DepthErrors, per_image_subset_errors, subset_suffix
from odmv.training.module import subset_masks, write_test_outputs
from odmv.training.provenance import provenance


def classical_row(
    root: str | Path,
    out_dir: str | Path,
    resolution=None,
    split: str = "test",
    capture: Capture | None = None,
) -> dict:
    """Reconstruct every scene of ``split`` of the dataset at ``root`` classically, from the
    images resized to ``resolution`` as the networks see them (None: as stored); write and
    return its metrics (keys like a trained run's: ``test/mae_mm``, ..., ``test/coverage``).
    ``capture``: the images decoded per projector (None: every step of every frequency the
    camera resolves)."""
    t0 = time.perf_counter()
    m = load_manifest(root)
    if m.images != "full":
        raise DataError(f"{m.root}: the classical row needs the full sequences (images=full)")
    size = [m.height_px, m.width_px] if resolution is None else resolution
    spec = check_spec(m, m.views, size, None, None, with_stacks=True)
    h, w = spec.height_px, spec.width_px
    ids = split_scenes(m, None, 0)[split]
    cam = m.rig.camera_at(w, h)
    projectors = [m.rig.projectors()[v] for v in m.views]
    n_f, n_s = len(m.fringe.periods_px), m.fringe.steps
    options = twin_options(m)
    coarse_first = np.argsort(m.fringe.periods_px)[::-1]
    families = {s["id"]: str(s.get("family", "")) for s in m.scenes}
    metrics = {k: DepthErrors() for k in SUBSETS}
    covered = {k: [0.0, 0.0] for k in SUBSETS}
    rows, preds = [], {"scene_id": [], "pred_mm": [], "depth_mm": []}
    for sid in ids:
        raw = load_scene(m, sid, spec)
        stack = raw["fringe_stack"].reshape(len(m.views), n_f, n_s, h, w)
        if capture is None:
            depth = reconstruct_scene(stack[:, coarse_first], cam, projectors, options)
        else:
            depth = capture_depth(stack, m, capture, cam, projectors, list(m.views))
        gt = torch.from_numpy(raw["depth_mm"][None].astype(np.float32))
        pred = torch.from_numpy(np.nan_to_num(depth, nan=0.0)[None, None].astype(np.float32))
        ok = torch.from_numpy(np.isfinite(depth)[None, None]).float()
        subsets = {k: torch.from_numpy(raw[k][None]).float() for k in MASKS}
        masks = subset_masks({"valid": torch.isfinite(gt).float(), "depth_mm": gt} | subsets)
        reconstructed = {k: mask * ok for k, mask in masks.items()}
        row = {"scene": sid, "family": families.get(sid, "")}
        for k, v in per_image_subset_errors(pred, gt, reconstructed).items():
            if not k.startswith("pixels"):
                row[k] = float(v[0])
        for subset, mask in masks.items():
            # each subset's pixels, as a trained run's file counts them (the report picks the
            # figures' scenes by them)
            row[f"pixels{subset_suffix(subset)}"] = float(mask.sum())
            metrics[subset].update(pred, gt, reconstructed[subset])
            covered[subset][0] += float(reconstructed[subset].sum())
            covered[subset][1] += float(mask.sum())
            row[f"coverage{subset_suffix(subset)}"] = float(reconstructed[subset].sum()) / max(
                float(mask.sum()), 1.0
            )
        rows.append(row)
        preds["scene_id"].append([sid])
        preds["pred_mm"].append(depth[None].astype(np.float32))
        preds["depth_mm"].append(raw["depth_mm"].astype(np.float32))
    if not ids:
        raise DataError(f"{m.root}: the {split} split is empty")
    out = {}
    valid_pixels = covered["all"][1]
    for subset in SUBSETS:
        suffix = subset_suffix(subset)
        for name, value in metrics[subset].compute().items():
            if name != "pixels":
                out[f"test/{name}{suffix}"] = float(value)
        out[f"test/coverage{suffix}"] = covered[subset][0] / max(covered[subset][1], 1.0)
        if subset != "all":
            out[f"test/share{suffix}"] = covered[subset][1] / max(valid_pixels, 1.0)
    out.update(
        model="classical",
        views=list(m.views),
        **({"capture": capture.key, "images_per_projector": capture.images} if capture else {}),
        parameters=0,
        train_seconds=0.0,
        test_seconds=round(time.perf_counter() - t0, 1),
        scenes=len(ids),
        resolution=[h, w],
        **provenance(m.root),
    )
    out_dir = Path(out_dir)
    write_test_outputs(out_dir, rows, preds)
    write_json(out_dir / METRICS, portable_record(out, out_dir))
    return out
