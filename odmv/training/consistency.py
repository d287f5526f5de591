"""The label-free loss: how well a depth map explains the fringe images the rig captured.

A depth map, through the calibrated rig (odmv.classical.geometry), predicts the phase of every
view's fringe at every pixel. The image carries the true phase: I = A + B cos(phi) with an
offset A and an amplitude B that albedo, shading, ambient light and defocus set per pixel. In a
small window around each pixel the image is fitted, in closed form (least squares), as A + a
cos(phi_d) + b sin(phi_d) with phi_d the depth's phase: the fringe re-rendered from the depth
with its offset and amplitude fitted, i.e. the image demodulated with the depth's own phase as
the carrier. Its phase e = atan2(-b, a) is what the depth gets wrong, at the window's
resolution (``harmonics`` 2 adds cos(2 phi_d) and sin(2 phi_d) to the fit, for fringes that
projector gamma or gloss made other than a sinusoid); the loss is the circular distance 1 -
cos(e) over every view, so one depth must explain all of them where two or more projectors
light a pixel. It is zero at the true depth of a noise-free scene whose offset and amplitude
are constant over each window, rises with a depth offset as 1 - cos(2 pi offset / P) in the
projector, and sees the fringe order only modulo a period (about 11 mm of height on the twin):
it refines a depth that is right to within half a period; it cannot find the order.

Each pixel's weight (no gradient) is the fitted amplitude sqrt(a^2 + b^2) (none below
``min_amplitude``: shadow, no fringe) times the fit's R^2 to the power ``quality_power``: the
share of the window's intensity variance that the depth's fringe explains, which a uniform
phase error does not lower but a window across an edge, a shadow boundary or an albedo change
does, where the fitted phase is biased. Even so the loss is not minimal at the truth for a net
(on the nominal twin an unanchored fine-tune drifts from 0.130 to 0.147 mm in 50 steps), so
adaptation adds a trust region: ``anchor`` times the mean absolute change (mm) from the net it
started from, which small biased pulls do not overcome and large consistent ones (a plane
misplaced under defocus) do (experiments/results/adapt/notebook.md).

Why not the phase of Fourier-transform profilometry as the target: demodulated against the
reference plane's carrier, one image's phase is known only at the resolution of a fringe period
and scores 0.44 mm on the twin, three times the networks' error (docs/findings.md, section 6).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import torch
import torch.nn.functional as F

from odmv.classical.geometry import offset_from_depth, phase_from_depth

#: what adaptation fits the net to (ConsistencySettings.target; auto: classical where the
#: user's dataset holds the full sequences, else fringes)
TARGETS = ("auto", "fringes", "classical")


@dataclass(frozen=True)
class ConsistencySettings:
    """``window_px``: the fit's square window (odd, camera px; about half a fringe period on
    the camera: 5 at 64 px, where a period spans about 10 px). ``min_amplitude``: the fitted
    amplitude (linear intensity) below which a pixel carries no weight. ``quality_power``: the
    exponent of the fit's R^2 in the weight. ``anchor``: the trust region's weight per mm of
    mean absolute change from the starting net. ``harmonics``: the fringe's harmonics in the
    fit (1: a sinusoid; 2 takes up a fringe distorted by projector gamma or gloss, and wants a
    window of about a fringe period: 9 px at 64 px; ``auto``: chosen from the user's images
    before adapting, :func:`chosen_fit`). ``stale_mm``: the spread (std, mm) of the
    views' mean asked-for depth changes above which the calibration is taken to be stale
    (:func:`view_offsets_mm`). ``replay``: the weight of the starting net's own loss on
    batches of its own (labelled) training scenes, beside every batch of the user's: what it
    knew of the twin is kept (0: none). ``target``: ``fringes``, this module's loss on the one
    image per projector the net reads; ``classical``, the depth that phase shifting
    reconstructs from the user's full sequences (odmv.classical), where it reconstructs one,
    in the run's own depth loss: a label without ground truth, for users who capture the
    sequences of their adaptation scenes; ``auto``, classical where the dataset holds them
    (:func:`chosen_target`)."""

    window_px: int = 5
    harmonics: int | str = 1
    min_amplitude: float = 0.02
    quality_power: float = 4.0
    anchor: float = 0.02
    stale_mm: float = 0.05
    replay: float = 1.0
    target: str = "auto"

    def __post_init__(self):
        if self.target not in TARGETS:
            raise ValueError(f"adaptation.target: {self.target!r}; choose from {list(TARGETS)}")
        if self.window_px < 3 or self.window_px % 2 == 0:
            raise ValueError(f"adaptation.window_px: {self.window_px} must be odd and at least 3")
        if self.harmonics == "auto":
            pass
        elif (
            not isinstance(self.harmonics, int)
            or self.harmonics < 1
            or self.window_px < 2 * self.harmonics + 1
        ):
            raise ValueError(
                f"adaptation.harmonics: {self.harmonics} must be auto or at least 1, with "
                f"window_px at least 2 x harmonics + 1 (the fit's unknowns; window_px is "
                f"{self.window_px})"
            )
        for key in ("min_amplitude", "quality_power", "anchor", "stale_mm", "replay"):
            if getattr(self, key) < 0:
                raise ValueError(f"adaptation.{key}: {getattr(self, key)} must be >= 0")

    @classmethod
    def of(cls, values: dict) -> ConsistencySettings:
        """The settings among ``values`` (an ``adaptation`` config, which holds others too)."""
        return cls(**{k: values[k] for k in asdict(cls()) if k in values})


def _box(x: torch.Tensor, k: int) -> torch.Tensor:
    """Mean over a k x k window around each pixel (fewer pixels at the border)."""
    return F.avg_pool2d(x, k, stride=1, padding=k // 2, count_include_pad=False)


def _fit(
    fringes: torch.Tensor, phase_rad: torch.Tensor, window_px: int, harmonics: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The windowed least-squares fit of :func:`fringe_fit` -> (its coefficients a_1, b_1, a_2,
    b_2, ... as B x S x H x W x 2 ``harmonics``, its R^2 B x S x H x W), in float32."""
    with torch.autocast(fringes.device.type, enabled=False):
        image, phase = fringes.float(), phase_rad.float()
        k = window_px
        basis = [f(n * phase) for n in range(1, harmonics + 1) for f in (torch.cos, torch.sin)]
        means = [_box(x, k) for x in basis]
        mi = _box(image, k)
        # the centred normal equations, damped where the phase barely varies
        n = len(basis)
        pairs = {
            (i, j): _box(basis[i] * basis[j], k) - means[i] * means[j]
            for i in range(n)
            for j in range(i, n)
        }  # symmetric: each entry once
        normal = torch.stack([pairs[min(i, j), max(i, j)] for i in range(n) for j in range(n)], -1)
        normal = normal.unflatten(-1, (n, n))
        moments = torch.stack(
            [_box(x * image, k) - m * mi for x, m in zip(basis, means, strict=True)], -1
        )
        eye = torch.eye(n, device=image.device)
        coef = torch.linalg.solve(normal + 1e-6 * eye, moments.unsqueeze(-1)).squeeze(-1)
        ii = _box(image * image, k) - mi * mi
        r2 = ((coef * moments).sum(-1) / ii.clamp_min(1e-9)).clamp(0, 1)
        return coef, r2


def fringe_fit(
    fringes: torch.Tensor, phase_rad: torch.Tensor, window_px: int, harmonics: int = 1
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The windowed least-squares fit of each view's image (B x S x H x W, linear intensity)
    as A + sum over k = 1..``harmonics`` of a_k cos(k phase) + b_k sin(k phase) -> (its
    fundamental's phase e = atan2(-b_1, a_1) in rad, its amplitude sqrt(a_1^2 + b_1^2), the
    fit's R^2 in [0, 1]), each B x S x H x W; differentiable in ``phase_rad``. The harmonics
    take up what a fringe that is not a sinusoid (projector gamma, gloss) would otherwise
    leak into the fundamental's phase inside a window. Runs in float32."""
    coef, r2 = _fit(fringes, phase_rad, window_px, harmonics)
    a, b = coef[..., 0], coef[..., 1]
    return torch.atan2(-b, a), torch.sqrt(a * a + b * b + 1e-12), r2


def harmonic_sums(
    depth_mm: torch.Tensor, fringes: torch.Tensor, maps: torch.Tensor, settings
) -> tuple[torch.Tensor, torch.Tensor]:
    """How far the fringes are from a sinusoid, seen through ``depth_mm``'s phase: the
    windowed fit with two harmonics in a window of twice ``settings.window_px`` - 1 (about a
    fringe period), summed over the pixels of each view that the default fit weights -> (the
    sum of weight x second-harmonic amplitude, the sum of weight x first-harmonic amplitude),
    each S. Their quotient is the fringe's second harmonic relative to its fundamental: at
    the true depth 0.03-0.04 for the twin's sinusoids, 0.05-0.06 under defocus 1.5, 0.27
    under projector gamma 2.2 (experiments/fit_bias.py)."""
    with torch.no_grad():
        phase = phase_from_depth(depth_mm.float(), maps.float())
        coef, r2 = _fit(fringes, phase, 2 * settings.window_px - 1, 2)
        first = torch.sqrt(coef[..., 0].square() + coef[..., 1].square() + 1e-12)
        second = torch.sqrt(coef[..., 2].square() + coef[..., 3].square())
        w = _weights(first, r2, settings)
        return (w * second).sum((0, 2, 3)), (w * first).sum((0, 2, 3))


#: the second harmonic's share of the fundamental above which ``harmonics=auto`` fits two
#: harmonics: between the twin's sinusoids (under a net's depth 0.04 nominal, 0.08 defocus 1.5)
#: and its projector gamma 2.2 (0.26), a 3x margin each side (adapt/notebook.md, round 7)
SECOND_HARMONIC_SHARE = 0.15


def chosen_fit(settings: ConsistencySettings, share: float) -> ConsistencySettings:
    """``harmonics=auto`` resolved by the fringes' measured second-harmonic ``share``
    (:func:`harmonic_sums`): a sinusoid fit in ``window_px`` below
    :data:`SECOND_HARMONIC_SHARE`, else two harmonics in a window of about a fringe period
    (2 ``window_px`` - 1), where the sinusoid fit would be pulled off the truth."""
    if share < SECOND_HARMONIC_SHARE:
        return replace(settings, harmonics=1)
    return replace(settings, harmonics=2, window_px=2 * settings.window_px - 1)


#: what each ``auto`` of ``adaptation``'s lr, anchor and replay stands for, by target: the
#: fringe fit is a weak, noisy label that needs the trust region and the twin's replay to stay
#: where it was; the classical depth is a direct label that may move the net further (seed 1
#: under defocus 1.5: 81 % of the gap closed against 54 % with the fringe fit's settings, the
#: nominal twin +0.7 %; experiments/results/adapt/notebook.md, round 13). The supervised
#: fine-tune (the ceiling) reads the lr alone: the classical target's, so that label-free and
#: supervised are compared at one rate (at 1e-4 the ceiling fell behind the classical target).
TARGET_DEFAULTS = {
    "fringes": {"lr": 1.0e-4, "anchor": 0.02, "replay": 1.0},
    "classical": {"lr": 3.0e-4, "anchor": 0.0, "replay": 0.3},
    "supervised": {"lr": 3.0e-4, "anchor": 0.0, "replay": 0.0},
}


def target_for(target: str, images: str) -> str:
    """``target=auto`` resolved by the user's dataset's ``images``: the classical
    reconstruction where it holds the full sequences (closer to the truth than the fringe
    fit on every shift measured: adapt notebook round 10), else the fringe fit."""
    if target != "auto":
        return target
    return "classical" if images == "full" else "fringes"


def resolved_adaptation(adaptation: dict, images: str) -> dict:
    """An ``adaptation`` config with its target resolved (:func:`target_for`) and each
    ``auto`` among lr, anchor and replay set to that target's :data:`TARGET_DEFAULTS`."""
    target = target_for(adaptation["target"], images)
    defaults = TARGET_DEFAULTS["supervised" if adaptation.get("supervised") else target]
    chosen = {k: v for k, v in defaults.items() if adaptation.get(k, "auto") == "auto"}
    return adaptation | {"target": target} | chosen


def _weights(amplitude, r2, settings: ConsistencySettings, available=None) -> torch.Tensor:
    with torch.no_grad():
        w = amplitude * (amplitude >= settings.min_amplitude) * r2**settings.quality_power
        return w if available is None else w * available[..., None, None]


def consistency_loss(
    depth_mm: torch.Tensor,
    fringes: torch.Tensor,
    maps: torch.Tensor,
    settings: ConsistencySettings,
    available: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """How far ``depth_mm`` (B x 1 x H x W) is from explaining the ``fringes`` (B x S x H x W,
    linear intensity) through the calibration ``maps`` (B x S x 6 x H x W): ``loss`` (the
    weighted mean of 1 - cos(e)), ``phase_rad`` (the weighted RMS of e, detached) and
    ``weighted`` (the share of view pixels with weight). ``available`` (B x S or None): a
    missing view carries no weight."""
    phase = phase_from_depth(depth_mm.float(), maps.float())
    error, amplitude, r2 = fringe_fit(fringes, phase, settings.window_px, settings.harmonics)
    weight = _weights(amplitude, r2, settings, available)
    total = weight.sum().clamp_min(1e-12)
    loss = (weight * (1 - torch.cos(error))).sum() / total
    with torch.no_grad():
        rms = torch.sqrt((weight * error.square()).sum() / total)
    return {"loss": loss, "phase_rad": rms, "weighted": (weight > 0).float().mean()}


def view_corrections_mm(
    depth_mm: torch.Tensor, fringes: torch.Tensor, maps: torch.Tensor, settings
) -> tuple[torch.Tensor, torch.Tensor]:
    """The depth change (mm) each view's fringe asks for at every pixel (B x S x H x W): its
    fitted phase error as an offset in its projector, through the triangulation; and the
    pixels' weights. Right calibration: where two views light a pixel they ask for the same
    change. A stale one (a projector moved after calibrating) makes them disagree."""
    with torch.no_grad():
        depth_mm, maps = depth_mm.float(), maps.float()
        phase = phase_from_depth(depth_mm, maps)
        error, amplitude, r2 = fringe_fit(fringes, phase, settings.window_px, settings.harmonics)
        delta = offset_from_depth(depth_mm, maps)
        # d depth / d offset of depth = ref + delta g / (1 - delta h)
        slope = maps[:, :, 3] / (1 - delta * maps[:, :, 4]) ** 2
        change = error / (2 * torch.pi) * maps[:, :, 1] * slope
        return change, _weights(amplitude, r2, settings)


def view_offsets_mm(
    depth_mm: torch.Tensor, fringes: torch.Tensor, maps: torch.Tensor, settings
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each view's weighted mean over a batch of the depth change it asks for (S, mm;
    :func:`view_corrections_mm`), and each view's total weight (S). With the rig as
    calibrated, a net's error moves every view alike (under defocus the views of the twin ask
    for +0.10 to +0.12 mm); a projector that moved after calibrating asks for its own (the
    twin's projectors turned by 0.1 degree: -0.15 to +0.17 mm)."""
    change, w = view_corrections_mm(depth_mm, fringes, maps, settings)
    total = w.sum((0, 2, 3))
    return (w * change).sum((0, 2, 3)) / total.clamp_min(1e-12), total
