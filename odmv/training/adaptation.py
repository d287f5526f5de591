"""Label-free adaptation (``adapt=true``): what comes before it, the fit chosen from the
user's fringes (``adaptation.harmonics=auto``) and the calibration check.

The consistency loss (odmv.training.consistency) fits a depth to the fringes through the rig's
calibration. If the rig moved after it was calibrated, no depth explains every view, and
fitting one would teach the net the wrong geometry. So before adapting, the net it starts from
is run on the user's scenes and each view's mean asked-for depth change is measured: a net's
own error moves every view alike, a stale calibration moves each view its own way. Where the
target is the classical reconstruction of the user's sequences, each projector's own
phase-shifting depth is compared with the others' instead: no net's error enters, and every
projector the user captured counts, so a net that reads one view is checked too. Where the
views' spread exceeds ``stale_mm`` the run stops and says so; with one projector there is
nothing to compare, and the run says that.

A fringe that is not a sinusoid (projector gamma) pulls the default sinusoid fit off the true
depth; the starting net's depth shows how much second harmonic the user's fringes carry, and
``harmonics=auto`` fits two harmonics where that is large.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from odmv.training.consistency import harmonic_sums, view_offsets_mm


class StaleCalibrationError(ValueError):
    """The views disagree on the depth: the calibration no longer describes the rig."""


def _depths(module, loader, max_batches: int):
    """``module``'s depth (mm), the linear fringes and the calibration maps of up to
    ``max_batches`` batches of ``loader``, in eval mode without gradients."""
    was_training = module.training
    module.eval()
    try:
        with torch.no_grad():
            for i, batch in enumerate(loader):
                if i >= max_batches:
                    break
                depth_mm = module.depth_mm(module.run(batch))
                yield (
                    depth_mm,
                    module.norm.intensity(batch["fringes"].float()),
                    batch["calibration"],
                )
    finally:
        module.train(was_training)


def view_offsets(
    module, loader, views: list[str], window_px: int, max_batches: int = 8
) -> dict[str, float]:
    """Each view's mean asked-for depth change (mm) of ``module``'s depth over up to
    ``max_batches`` batches of ``loader``, by view name (``views``: the batches' views),
    measured with the sinusoid fit in ``window_px`` whatever fit the adaptation uses: a bias
    common to every view cancels in the check, and the sinusoid's per-view means are the
    steadiest (under projector gamma 2.2 the views' spread is 0.007-0.020 mm with it and 0.04-0.07
    mm with the 9 px two-harmonic fit, whose 0.05 mm threshold it crossed; adapt notebook
    round 9)."""
    fit = replace(module.adapt, harmonics=1, window_px=window_px)
    sums, totals = 0.0, 0.0
    for depth_mm, linear, maps in _depths(module, loader, max_batches):
        mean, total = view_offsets_mm(depth_mm, linear, maps, fit)
        sums, totals = sums + mean * total, totals + total
    return {v: float(s / t) for v, s, t in zip(views, sums, totals, strict=True) if t > 0}


def second_harmonic_share(module, loader, settings, max_batches: int = 8) -> float:
    """The fringes' second harmonic relative to their fundamental over up to ``max_batches``
    batches of ``loader``, seen through ``module``'s depth (:func:`harmonic_sums`): what
    ``adaptation.harmonics=auto`` chooses its fit by."""
    second, first = 0.0, 0.0
    for depth_mm, linear, maps in _depths(module, loader, max_batches):
        s, f = harmonic_sums(depth_mm, linear, maps, settings)
        second, first = second + s.sum(), first + f.sum()
    return float(second / first) if float(first) > 0 else 0.0


#: What the calibration check compares, by source: the starting net's depth through each
#: view's fringe, or each projector's classical depth (target=classical) against the others'.
CHECK_SOURCES = {
    "net": "the views ask for",
    "classical": "each projector's phase-shifting depth off the others'",
}


def view_spread_mm(offsets: dict[str, float]) -> float | None:
    """The spread (population std, mm) of the views' ``offsets``; None with fewer than two
    views (one view cannot disagree with itself)."""
    if len(offsets) < 2:
        return None
    return float(torch.tensor(list(offsets.values()), dtype=torch.float64).std(unbiased=False))


def check_calibration(
    offsets: dict[str, float], stale_mm: float, where, source: str = "net"
) -> float | None:
    """The views' :func:`view_spread_mm` of ``offsets`` (measured as :data:`CHECK_SOURCES`
    ``[source]`` says); raises StaleCalibrationError naming ``where`` if it exceeds
    ``stale_mm``."""
    spread = view_spread_mm(offsets)
    if spread is not None and spread > stale_mm:
        per_view = ", ".join(f"{v} {x:+.3f}" for v, x in offsets.items())
        cause = (
            "the calibration no longer describes the rig (a projector moved?); recalibrate and "
            "convert the captures again"
            if source == "classical"
            else "either the calibration no longer describes the rig (a projector moved?), or "
            "the net cannot tell (a weakly trained net's views disagree by themselves); the "
            "captured sequences tell the two apart, as their check measures each projector "
            "without the net (convert format=sequences, then adapt): recalibrate if they "
            "disagree too, else train the net further"
        )
        raise StaleCalibrationError(
            f"{where}: the views disagree on the depth ({CHECK_SOURCES[source]}: {per_view} "
            f"mm; spread {spread:.3f} mm > adaptation.stale_mm={stale_mm}): {cause}; or "
            "adaptation.check_calibration=false to adapt anyway"
        )
    return spread


#: An adapted run's test figures on scenes without ground truth, what each means, and how
#: to print its value
LABEL_FREE = {
    "classical_mae_mm": ("MAE against the classical reconstruction", "{:.4f} mm"),
    "covered": ("pixels the classical reconstruction covers", "{:.1%}"),
    "phase_rad": ("RMS phase error of the fringe fit", "{:.4f} rad"),
    "change_mm": ("mean change from the starting net", "{:.4f} mm"),
    "loss": ("the loss minimised (net units)", "{:.4f}"),
}


def adaptation_lines(metrics: dict, split: str = "test") -> list[tuple[str, str]]:
    """(meaning, value with unit) of each of ``split``'s label-free figures a record holds."""
    return [
        (meaning, form.format(metrics[f"{split}/{key}"]))
        for key, (meaning, form) in LABEL_FREE.items()
        if f"{split}/{key}" in metrics
    ]
