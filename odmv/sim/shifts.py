"""Shifts: the twin rendered through a rig, optics or surfaces that differ from the nominal ones.

A shifted dataset shows the same scenes as a nominal one, but its images come from a perturbed
rig while its manifest keeps the nominal calibration: what a user's calibration, made before the
rig drifted, says. The reference-phase input and the classical method therefore use the nominal
rig, as they would on the shop floor. Each shift has one strength; at its nominal strength it
renders the nominal images byte for byte.

Every shift is one entry of :data:`KINDS`: its unit, nominal and example strengths, the two
strengths the robustness study renders, what it changes and how (the rig, the optics and
sensor, or the surfaces). ``shift=NAME`` (a config option registered from the table by
odmv.config), the simulator and the robustness study read it.

The random axes and directions are drawn from ``seed`` per projector, the same for every scene.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from odmv.rig import VIEW_NAMES, Projector, Rig
from odmv.sim.render import RenderConfig


class Kind(NamedTuple):
    """One kind of shift. ``rig(rig, x, seed)`` or ``render(cfg, x)`` applies it at strength
    ``x`` where it changes the rig or the optics and sensor; the surface shifts (texture,
    gloss, dead_view) reach the renderer as :class:`Applied`'s fields."""

    unit: str
    nominal: float | str | None  # the strength that renders the nominal images
    example: float | str | None  # shift=NAME's strength
    study: tuple  # the strengths the robustness study renders (a drift and a larger one)
    what: str
    rig: Callable | None = None
    render: Callable | None = None
    signed: bool = False  # negative strengths allowed
    positive: bool = False  # strength must be above 0


def _zoom(rig: Rig, x: float, seed: int) -> Rig:  # a moved-projector rig keeps its moves
    return replace(
        rig, camera=replace(rig.camera, focal_length_mm=rig.camera.focal_mm * (1 + x / 100))
    )


def _moved(rig: Rig, seed: int) -> MovedProjectorsRig:
    return (
        rig
        if isinstance(rig, MovedProjectorsRig)
        else MovedProjectorsRig(rig.camera, rig.projector, seed=seed)
    )


#: every shift, in the order the robustness report lists them: the one place they are declared
KINDS: dict[str, Kind] = {
    "none": Kind(
        unit="",
        nominal=None,
        example=None,
        study=(),
        what="the nominal twin: the images come from the rig the manifest describes",
    ),
    "projector_rotation": Kind(
        unit="deg",
        nominal=0.0,
        example=0.5,
        study=(0.02, 0.1),
        what="each projector turned about its centre by X, about its own random axis (shift.seed)",
        rig=lambda rig, x, seed: replace(_moved(rig, seed), rotation_deg=x, seed=seed),
    ),
    "projector_shift": Kind(
        unit="mm",
        nominal=0.0,
        example=1.0,
        study=(0.05, 0.2),
        what="each projector's centre moved X in its own random direction (shift.seed)",
        rig=lambda rig, x, seed: replace(_moved(rig, seed), shift_mm=x, seed=seed),
    ),
    "camera_focal": Kind(
        unit="%",
        nominal=0.0,
        example=1.0,
        study=(0.2, 1),
        what="the camera's focal length +X (a zoom or refocus after calibration)",
        rig=_zoom,
        signed=True,
    ),
    "gamma": Kind(
        unit="exponent",
        nominal=1.0,
        example=2.2,
        study=(1.5, 2.2),
        what="the projector's intensity curve: the pattern is (A + B cos phi)^X, uncompensated",
        render=lambda cfg, x: replace(cfg, projector_gamma=x),
        positive=True,
    ),
    "defocus": Kind(
        unit="output px",
        nominal=0.0,
        example=1.0,
        study=(0.7, 1.5),
        what="Gaussian blur of the optical image, sigma X",
        render=lambda cfg, x: replace(cfg, defocus_sigma_px=x),
    ),
    "ambient": Kind(
        unit="of full scale",
        nominal=0.0,
        example=0.2,
        study=(0.1, 0.3),
        what="ambient light +X of the sensor's full scale",
        render=lambda cfg, x: replace(cfg, ambient=cfg.ambient + x),
    ),
    "noise": Kind(
        unit="x nominal std",
        nominal=1.0,
        example=4.0,
        study=(2, 4),
        what="photon and read noise X times their nominal std",
        render=lambda cfg, x: replace(
            cfg, read_noise=cfg.read_noise * x, full_well_e=cfg.full_well_e / x**2
        ),
    ),
    "exposure": Kind(
        unit="x irradiance",
        nominal=1.0,
        example=1.5,
        study=(0.6, 1.5),
        what="every irradiance times X; above the sensor's full scale the images saturate",
        render=lambda cfg, x: replace(
            cfg, ambient=cfg.ambient * x, projector_irradiance=cfg.projector_irradiance * x
        ),
        positive=True,
    ),
    "texture": Kind(
        unit="contrast",
        nominal=0.0,
        example=0.5,
        study=(0.3, 0.6),
        what="printed marks (labels, silkscreen) on the parts: albedo times 1 - X on a mark",
    ),
    "gloss": Kind(
        unit="of irradiance",
        nominal=0.0,
        example=1.0,
        study=(0.5, 1.5),
        what="a specular lobe of each projector on every surface, X of its irradiance at peak",
    ),
    "dead_view": Kind(
        unit="view",
        nominal=None,
        example="down",
        study=VIEW_NAMES,
        what="the projector named X gives no light: its images are ambient only",
    ),
}
#: each shift's nominal strength (None for dead_view: no projector dead)
NOMINAL: dict[str, float | str | None] = {name: k.nominal for name, k in KINDS.items()}


class ShiftError(ValueError):
    """A one-line error about a shift's name or strength."""


@dataclass(frozen=True)
class Shift:
    name: str = "none"
    strength: float | str | None = None  # None: the shift's nominal strength
    seed: int = 0

    def __post_init__(self):
        if self.name not in NOMINAL:
            raise ShiftError(f"shift {self.name!r} unknown; choose from {', '.join(NOMINAL)}")
        if self.name == "dead_view":
            if self.strength is not None and self.strength not in VIEW_NAMES:
                raise ShiftError(
                    f"shift dead_view: strength {self.strength!r} is not a view; "
                    f"name one of {', '.join(VIEW_NAMES)}"
                )
            return
        if self.strength is None or self.name == "none":
            return
        try:
            value = float(self.strength)
        except (TypeError, ValueError):
            raise ShiftError(
                f"shift {self.name}: strength {self.strength!r} is not a number"
            ) from None
        kind = KINDS[self.name]
        if not math.isfinite(value) or (value <= 0 and kind.positive):
            raise ShiftError(f"shift {self.name}: strength {value} is out of range")
        if value < 0 and not kind.signed:
            raise ShiftError(f"shift {self.name}: strength {value} must not be negative")
        object.__setattr__(self, "strength", value)

    @property
    def value(self):
        """The strength in effect (the nominal one where none is given)."""
        return NOMINAL[self.name] if self.strength is None else self.strength

    @property
    def nominal(self) -> bool:
        return self.value == NOMINAL[self.name]

    def label(self) -> str:
        """``nominal``, or ``NAME:STRENGTH`` as :func:`parse_shift` reads it."""
        if self.nominal:
            return "nominal"
        value = f"{self.value:g}" if isinstance(self.value, float) else self.value
        return f"{self.name}:{value}"

    def to_dict(self) -> dict:
        return {"name": self.name, "strength": self.value, "seed": self.seed}

    # -------------------------------------------------------------------------- applied
    def rig(self, rig: Rig) -> Rig:
        """The rig that renders the images (the manifest keeps ``rig``)."""
        moves = KINDS[self.name].rig
        return rig if self.nominal or moves is None else moves(rig, self.value, self.seed)

    def render(self, cfg: RenderConfig) -> RenderConfig:
        """The optics and sensor that render the images."""
        changes = KINDS[self.name].render
        return cfg if self.nominal or changes is None else changes(cfg, self.value)

    @property
    def texture_contrast(self) -> float:
        return float(self.value) if self.name == "texture" else 0.0

    @property
    def gloss(self) -> float:
        return float(self.value) if self.name == "gloss" else 0.0

    @property
    def dead_view(self) -> str | None:
        return self.value if self.name == "dead_view" else None


NOMINAL_SHIFT = Shift()


@dataclass(frozen=True)
class Applied:
    """What a set of shifts does to a render: the rig and optics that render the images, the
    surfaces' texture and gloss, and the dead projector (odmv.sim.render.render_scene)."""

    rig: Rig
    render: RenderConfig
    texture: float = 0.0
    gloss: float = 0.0
    dead_view: str | None = None


def apply(shifts, rig: Rig, cfg: RenderConfig) -> Applied:
    """``shifts`` (one Shift or several, of distinct names) applied together to the nominal
    ``rig`` and ``cfg``."""
    shifts = [shifts] if isinstance(shifts, Shift) else list(shifts)
    names = [s.name for s in shifts if s.name != "none"]
    if len(set(names)) < len(names):
        raise ShiftError(f"shifts {names}: each shift at most once")
    out = Applied(rig, cfg)
    for s in shifts:
        out = replace(
            out,
            rig=s.rig(out.rig),
            render=s.render(out.render),
            texture=out.texture or s.texture_contrast,
            gloss=out.gloss or s.gloss,
            dead_view=out.dead_view or s.dead_view,
        )
    return out


def parse_shift(text: str, seed: int = 0) -> Shift:
    """``NAME:STRENGTH`` (or ``NAME`` for its nominal strength, ``none``) as a Shift."""
    name, _, strength = str(text).partition(":")
    return Shift(name, strength or None, seed)


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def _axis_angle(axis: np.ndarray, deg: float) -> np.ndarray:
    """Rotation matrix (Rodrigues) about a unit axis."""
    a = math.radians(deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


@dataclass(frozen=True)
class MovedProjectorsRig(Rig):
    """A rig whose projectors are turned about their centres (``rotation_deg``, each about its
    own random axis) or moved (``shift_mm``, each in its own random direction); the draws come
    from ``seed`` and the projector's name."""

    rotation_deg: float = 0.0
    shift_mm: float = 0.0
    seed: int = field(default=0)

    def projectors(self) -> dict[str, Projector]:
        out = {}
        for k, (name, p) in enumerate(super().projectors().items()):
            rng = np.random.default_rng([self.seed, k])
            axis, direction = _random_unit(rng), _random_unit(rng)
            R = p.R @ _axis_angle(axis, self.rotation_deg).T if self.rotation_deg else p.R
            centre = p.center + self.shift_mm * direction
            out[name] = replace(p, R=R, t=-R @ centre)
        return out
