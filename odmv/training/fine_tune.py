"""What a label-free fine-tune (``adapt=true``) does before it fits, on its starting net and
the user's scenes: the target it trains on, the fringe fit chosen by the second harmonic
(``adaptation.harmonics=auto``), the classical targets reconstructed from full sequences, and
the calibration check, refused where the projectors disagree (odmv.training.adaptation)."""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from odmv.cli import rank_zero_print
from odmv.data.classical import classical_depths
from odmv.io.atomic import write_json
from odmv.io.runfolder import CALIBRATION_CHECK
from odmv.training.adaptation import (
    CHECK_SOURCES,
    check_calibration,
    second_harmonic_share,
    view_offsets,
)
from odmv.training.consistency import SECOND_HARMONIC_SHARE, chosen_fit, target_for
from odmv.training.module import FPPModule, load_module


def prepare_adaptation(cfg: DictConfig, dm, module: FPPModule, resumed: bool, out_dir: Path):
    """The data set up, the target and fit set on ``module``, the calibration checked (once,
    on the starting net: a ``resumed`` run reads its check back); returns what the run's
    record says of them."""
    dm.prepare_data()
    dm.setup("fit")
    module.norm = dm.norm  # as the trainer's setup will set it
    target = target_for(module.adapt.target, dm.manifest.images)
    module.adapt = replace(module.adapt, target=target)
    said = {"target": module.adapt.target}
    if module.adapt.target == "fringes" and module.adapt.harmonics == "auto":
        said |= _chosen_fit(cfg, dm, module)  # resumed runs choose again
    classical_offsets = None
    if module.adapt.target == "classical":  # resumed runs decode again
        covered, classical_offsets = _classical_targets(dm, module)
        said |= covered
    if resumed:
        return said | _recorded_check(out_dir)
    check = _checked_calibration(cfg, dm, module, classical_offsets)
    write_json(out_dir / CALIBRATION_CHECK, check)
    return said | check


def _chosen_fit(cfg: DictConfig, dm, module: FPPModule) -> dict:
    """``adaptation.harmonics=auto``: the fit chosen by the second harmonic of the held-out
    scenes' fringes under the starting net's depth (the same net on a resumed run), set on
    ``module``; returns the share and the fit for the run's record. The torch random state is
    left as it was, so the run trains as one that named the fit."""
    with torch.random.fork_rng(devices=[]):
        start = load_module(cfg.init_from)
        start.norm = dm.norm  # the run reads images as its start did
        share = second_harmonic_share(start, dm.val_dataloader(), module.adapt)
    module.adapt = chosen_fit(module.adapt, share)
    a = module.adapt
    rank_zero_print(
        f"fringe fit: second harmonic {share:.3f} of the fundamental "
        f"({'>=' if a.harmonics == 2 else '<'} {SECOND_HARMONIC_SHARE}): {a.harmonics} "
        f"harmonic{'s' if a.harmonics > 1 else ''} in {a.window_px} px windows"
    )
    return {"second_harmonic_share": round(share, 4), "fit": f"{a.window_px}:{a.harmonics}"}


def _classical_targets(dm, module: FPPModule) -> tuple[dict, dict[str, float]]:
    """``adaptation.target=classical``: every scene of the user's dataset reconstructed by
    phase shifting from its full sequences, at the net's size, set on ``module`` as its
    targets; returns the share of pixels reconstructed for the run's record and each of the
    dataset's projectors' mean deviation from the others (mm; the calibration check's)."""
    t0 = time.perf_counter()
    ids = [sid for split in dm.splits.values() for sid in split]
    size = (dm.spec.height_px, dm.spec.width_px)
    depths, offsets = classical_depths(dm.manifest, ids, size)
    module.classical_mm = {sid: torch.from_numpy(d.astype(np.float32)) for sid, d in depths.items()}
    covered = float(np.mean([np.isfinite(d).mean() for d in depths.values()]))
    rank_zero_print(
        f"classical target: {len(ids)} scenes reconstructed by phase shifting in "
        f"{time.perf_counter() - t0:.0f} s, {100 * covered:.0f} % of their pixels"
    )
    return {"classical_covered": round(covered, 4)}, offsets


def _recorded_check(out_dir: Path) -> dict:
    """The calibration check a fine-tune made on its starting net, as its first start wrote it
    (a run begun before the check was kept has none)."""
    path = out_dir / CALIBRATION_CHECK
    return json.loads(path.read_text()) if path.is_file() else {}


def _checked_calibration(
    cfg: DictConfig, dm, module: FPPModule, classical_offsets: dict[str, float] | None
) -> dict:
    """Before adapting: where the target is classical, each of the dataset's projectors' own
    depth against the others' (``classical_offsets``: every projector the user captured,
    whatever views the net reads); else each view's mean asked-for depth change of the
    starting net on the held-out scenes. Refused (StaleCalibrationError) where the views
    disagree by more than ``adaptation.stale_mm``; returns them for the run's record."""
    if classical_offsets is not None:
        source, offsets = "classical", classical_offsets
    else:
        source = "net"
        views = list(dm.spec.views)
        offsets = view_offsets(module, dm.val_dataloader(), views, cfg.adaptation.window_px)
    spread = None
    if cfg.adaptation.check_calibration:
        spread = check_calibration(offsets, cfg.adaptation.stale_mm, dm.root, source)
    shown = ", ".join(f"{v} {x:+.3f}" for v, x in offsets.items())
    if len(offsets) < 2:
        rank_zero_print(
            f"calibration check: not possible with one view ({shown} mm): a projector "
            "moved since calibrating would go unseen"
            + (
                ""
                if source == "classical"
                else "; a dataset with the full sequences checks every projector"
            )
        )
    else:
        rank_zero_print(
            f"calibration check ({CHECK_SOURCES[source]}): {shown} mm"
            + ("" if spread is None else f" (spread {spread:.3f} mm <= {cfg.adaptation.stale_mm})")
        )
    return {"calibration_check": source, "view_offsets_mm": offsets, "view_spread_mm": spread}
